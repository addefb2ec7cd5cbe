"""The catalogue steps of a site preprocess config, run in-process on an AxisManager.

A campaign runs ``transient_find``, ``transient_cuts`` and ``transient_fit`` exactly as the site
pipeline configures them, but on AxisManagers it builds itself (a noise-only observation, a
window around one injected crossing), without saving to an archive. Detections come back as an
astropy table with the columns (and units) of ``so-transients catalog``.
"""
from __future__ import annotations

import copy

import numpy as np
from astropy import units as u
from astropy.table import Table, vstack
from sotodlib import core
from sotodlib.preprocess import Pipeline

CATALOG_STEPS = ("transient_find", "transient_cuts", "transient_fit")
DETECTION_COLUMNS = {  # detection column -> (transient_candidates field, unit)
    "bandpass": ("bandpass", None), "wafer_slot": ("wafer_slot", None),
    "t_peak": ("t_peak", u.s), "ra": ("fit_ra", u.rad), "dec": ("fit_dec", u.rad),
    "ra_err": ("ra_err", u.rad), "dec_err": ("dec_err", u.rad), "flux": ("flux", u.mJy),
    "flux_err": ("flux_err", u.mJy), "snr_fit": ("snr_fit", None), "n_dets": ("n_dets", None),
    "snr_max": ("snr_max", None),
}


def split_pipe(process_pipe):
    """(steps up to and including ``transient_filter``, the catalogue steps)."""
    names = [step["name"] for step in process_pipe]
    if "transient_filter" not in names:
        raise ValueError("the preprocess config has no transient_filter step")
    cut = names.index("transient_filter") + 1
    return process_pipe[:cut], [s for s in process_pipe[cut:] if s["name"] in CATALOG_STEPS]


class CatalogSearch:
    """``transient_find`` -> ``transient_cuts`` -> ``transient_fit`` from config entries,
    with saving and plotting off; ``error_scale`` fixes the fit's error scale."""

    def __init__(self, steps, error_scale=None):
        self.steps = []
        for entry in steps:
            entry = copy.deepcopy(entry)
            entry["save"] = False
            entry["plot"] = False
            if entry["name"] == "transient_fit" and error_scale is not None:
                entry.setdefault("calc", {})["error_scale"] = float(error_scale)
            self.steps.append(Pipeline.PIPELINE[entry["name"]](entry))

    def run(self, aman, obs_id="") -> Table:
        """Run the steps on ``aman`` (which holds ``transient_snr`` and ``transient_filter``);
        returns its detections."""
        proc_aman = core.AxisManager(aman.dets, aman.samps)
        for step in self.steps:
            step.calc_and_save(aman, proc_aman)
        return detections(aman, obs_id)


def stack(tables) -> Table:
    """``vstack`` of detection tables, skipped for a single one (it costs ~5 ms per call)."""
    return tables[0] if len(tables) == 1 else vstack(tables)


def detections(aman, obs_id="") -> Table:
    """Detected candidates of ``aman.transient_candidates`` as a table."""
    cands = aman.transient_candidates
    keep = (np.flatnonzero(np.asarray(cands.detected, bool)) if "detected" in cands._fields
            else np.zeros(0, int))
    table = Table()
    table["obs_id"] = np.full(len(keep), obs_id, dtype="U64")
    for name, (source, unit) in DETECTION_COLUMNS.items():
        values = np.asarray(cands[source])[keep] if source in cands._fields else np.zeros(0)
        table[name] = values.astype(str) if values.dtype.kind in "USO" else values
        if unit is not None:
            table[name].unit = unit
    return table
