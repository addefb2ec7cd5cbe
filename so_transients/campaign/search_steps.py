"""The search steps of a site preprocess config, run in-process on an AxisManager.

A campaign runs ``transient_find``, ``transient_cuts`` and ``transient_fit`` exactly as the site
pipeline configures them, but on AxisManagers it builds itself (a noise-only observation, a
window around one injected crossing), without saving to an archive. Detections come back as an
astropy table with columns (and units) of the candidate schema.
"""
from __future__ import annotations

import copy
import dataclasses
import logging

import numpy as np
from astropy.table import Table, vstack
from sotodlib import core
from sotodlib.preprocess import Pipeline

from so_transients.common import candidates
from so_transients.detect.find import FindConfig
from so_transients.detect.error_scale import ErrorScale
from so_transients.coherent.config import CoherentConfig, stacking_of
from so_transients.preprocess.step_settings import step_of, step_setting

#: The steps a campaign runs on its windows: transient_significance needs whole scans for its
#: time slides, so the fast path leaves it out (it reports, and cuts, nothing there), except
#: without slides for a paper-mode false-alarm budget (:func:`with_coherent_snr`).
SEARCH_STEPS = tuple(s for s in candidates.STEPS if s != "transient_significance")
#: Columns of a campaign's detection tables (besides ``obs_id``); ``real_score`` (NaN without
#: a ``score_model``) lets the thresholds at any cut on the score be found from one campaign.
DETECTION_COLUMNS = ("bandpass", "wafer_slot", "t_peak", "ra", "dec", "ra_err", "dec_err",
                     "flux", "flux_err", "snr_fit", "n_dets", "snr_max", "map_z",
                     "coherent_snr", "n_crossings", "real_score")


def split_pipe(process_pipe):
    """(steps up to and including ``transient_filter``, the search steps)."""
    names = [step["name"] for step in process_pipe]
    if "transient_filter" not in names:
        raise ValueError("the preprocess config has no transient_filter step")
    cut = names.index("transient_filter") + 1
    return process_pipe[:cut], [s for s in process_pipe[cut:] if s["name"] in SEARCH_STEPS]


def step_settings(search_steps, config_class):
    """The settings of the search step ``config_class`` configures (``FindConfig`` or
    ``CoherentConfig`` for ``transient_find``, ``FitConfig`` for ``transient_fit``, ...)
    among the steps' config entries."""
    name = step_of(config_class)
    entry = next((s for s in search_steps if s["name"] == name), None)
    if entry is None:
        raise ValueError(f"the preprocess config has no {name} step")
    return step_setting(config_class, entry.get("calc"))


def with_coherent_snr(search_steps, settings) -> list:
    """The search steps with ``transient_significance`` (``settings``: its
    :class:`~so_transients.significance.far.SignificanceConfig`) before ``transient_fit``,
    without time slides or a ``max_far`` cut: every candidate gets its ``coherent_snr`` (the
    statistic the campaign's pooled background turns into a ``far``, :mod:`.far_budget`),
    and ``transient_fit`` still decides ``detected``."""
    calc = {**dataclasses.asdict(settings), "n_slides": 0, "max_far": None}
    return before_fit(search_steps, {"name": "transient_significance", "calc": calc})


def before_fit(steps, entry) -> list:
    """``steps`` (config entries) with ``entry`` inserted before ``transient_fit`` (at the
    end without one), where ``transient_significance`` belongs."""
    names = [step["name"] for step in steps]
    at = names.index("transient_fit") if "transient_fit" in names else len(names)
    return steps[:at] + [entry] + steps[at:]


class SearchSteps:
    """``transient_find`` -> ``transient_cuts`` -> ``transient_fit`` from config entries,
    with saving and plotting off; ``error_scale`` (one number, or an
    :class:`~so_transients.detect.error_scale.ErrorScale`) fixes the fit's error scale."""

    def __init__(self, steps, error_scale=None):
        names = [entry["name"] for entry in steps]
        #: ``transient_find``'s sweep-stacking window (s; None: no stacking)
        self.stack_window = (_stacking_window(steps) if "transient_find" in names else None)
        self.steps = []
        for entry in steps:
            entry = copy.deepcopy(entry)
            entry["save"] = False
            entry["plot"] = False
            if entry["name"] == "transient_fit" and error_scale is not None:
                calc = entry.get("calc")
                entry["calc"] = {**(calc if isinstance(calc, dict) else {}),
                                 "error_scale": ErrorScale.of(error_scale).as_list()}
            self.steps.append(Pipeline.PIPELINE[entry["name"]](entry))

    def run(self, aman, obs_id="", fitted=False) -> Table:
        """Run the steps on ``aman`` (which holds ``transient_snr`` and ``transient_filter``);
        returns its detections (``fitted``: every candidate fitted, with ``detected``). The
        steps' per-group INFO and WARNING lines are not shown: a campaign's windows are
        seconds long by design, not short observations."""
        proc_aman = core.AxisManager(aman.dets, aman.samps)
        steps_log = logging.getLogger("so_transients")
        level = steps_log.level
        steps_log.setLevel(logging.ERROR)
        try:
            for step in self.steps:
                step.calc_and_save(aman, proc_aman)
        finally:
            steps_log.setLevel(level)
        return detections(aman, obs_id, fitted)


def stack(tables) -> Table:
    """``vstack`` of detection tables, skipped for a single one (it costs ~5 ms per call)."""
    return tables[0] if len(tables) == 1 else vstack(tables)


def detections(aman, obs_id="", fitted=False) -> Table:
    """Detected candidates of ``aman.transient_candidates`` as a table; ``fitted``: every
    candidate whose fit converged (at any S/N), with the ``detected`` column."""
    cands = aman.transient_candidates
    chosen = "fit_ok" if fitted else "detected"
    keep = (np.flatnonzero(np.asarray(cands[chosen], bool)) if chosen in cands._fields
            else np.zeros(0, int))
    table = Table()
    table["obs_id"] = np.full(len(keep), obs_id)
    for name in DETECTION_COLUMNS + (("detected",) if fitted else ()):
        col = candidates.BY_NAME[name]
        # a step that did not run (transient_significance) leaves its columns NaN
        values = (np.asarray(cands[name])[keep] if name in cands._fields
                  else np.full(len(keep), np.nan))
        table[name] = values.astype(str) if values.dtype.kind in "USO" else values
        if col.unit is not None:
            table[name].unit = col.unit
    return table


def _stacking_window(steps):
    """``transient_find``'s sweep-stacking window (s), None without stacking."""
    stacking = stacking_of(step_settings(steps, FindConfig), step_settings(steps, CoherentConfig))
    return None if stacking is None else stacking.stack_window
