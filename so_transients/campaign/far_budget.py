"""Detection at a false-alarm budget on the coherent statistic, in either search mode.

The paper's search, and the campaign's equal-rate thresholds (:mod:`.equal_rate`), rank
candidates by the beam fit's S/N, whose noise tail a few wafer-band-hours can only
extrapolate. The coherent statistic Z has a measured background: ``transient_significance``'s
time slides and sign-inverted data (:class:`so_transients.significance.far.Background`). With a
budget (``far_budget`` in the campaign config; on by default in coherent mode) the campaign
computes that background on each whole noise-only group, with the preprocess config's
``transient_significance`` settings (its defaults when the step is not listed), and keeps it
in the group's folder (``background.npz``). Pooled per band (live times add), it gives
``far(Z)`` per wafer-band-hour and the lowest Z whose ``far`` is the paper's rate
(``z_budget``). A flare is detected at that budget when one of its matched detections (the
search steps as configured) has a statistic at least ``z_budget``; the noise-only detections
above it are the measured check of the rate. The statistic (``CampaignConfig.far_statistic``):

* coherent mode: ``map_z``, the candidate's own map maximum (let the fit's ``min_snr`` be
  low: the fit only gives flux and position);
* paper mode: ``coherent_snr``, the highest Z near the candidate, as ``transient_significance``
  gives it (the search steps run that step without slides,
  :func:`.search_steps.with_coherent_snr`); the fit's S/N >= 5 still decides ``detected``, so
  a flare is detected as the site pipeline with ``max_far`` at the paper's rate would.

Either is in units of its own scan's measured spread (in a campaign: the injection window's
map), the background in units of the group's median spread; the two agree to the percent the
spread varies between scans.

With sweep stacking (``transient_find``'s ``stack_window``), a stacked detection
(``n_crossings`` > 1) has its own background, the slid and the sign-inverted maps' stacks
of the noise-only groups (``transient_significance``'s,
:func:`so_transients.significance.far.band_background`), and its own budget
``z_stack_budget``; single crossings and stacks each get half of the paper's rate, so that
together they keep to it.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.table import Table

from so_transients.coherent.config import CoherentConfig, stacking_of
from so_transients.detect.find import FindConfig, group_scans
from so_transients.common.scan_geometry import sample_rate
from so_transients.significance.far import Background, SignificanceConfig, band_background
from so_transients.campaign.equal_rate import PAPER_RATE_PER_WBH
from so_transients.campaign.search_steps import step_settings

log = logging.getLogger(__name__)
LIVE_COLUMNS = ("band", "obs_id", "wafer_slot", "slide_hours", "data_hours", "scale",
                "tail_from", "floor", "slide_floor", "stacked", "stack_slide_hours")


def group_background(state, search_steps, cfg: SignificanceConfig) -> Background:
    """The background of one prepared noise-only group (a :class:`.noise.GroupState`) over
    the scans ``transient_find`` searches."""
    aman = state.aman
    where = f"{state.group.obs_id} {state.group.wafer} {state.group.band}"
    find = step_settings(search_steps, FindConfig)
    coherent = step_settings(search_steps, CoherentConfig)
    scan, _ = group_scans(state.timestamps, aman.boresight.az, aman.boresight.el, find, where)
    f = aman.transient_filter
    dets = np.flatnonzero(~np.asarray(f.dead, bool))
    if not len(dets):
        raise ValueError(f"{where}: no live detector for the false-alarm background")
    beam = float(np.median(np.asarray(f.beam_sigma)[dets]))
    background, _ = band_background(state.snr, dets, state.timestamps, state.bore_q,
                                    state.xi[dets], state.eta[dets], scan,
                                    state.sigma_amp[dets], beam,
                                    sample_rate(state.timestamps, where), cfg,
                                    coherent.vetoes, stacking=stacking_of(find, coherent))
    return background


def save_background(background: Background, path, stamp):
    stacks = {k: getattr(background, k) for k in ("stacks", "stack_slides")
              if getattr(background, k) is not None}
    np.savez(path, slides=background.slides, inverted=background.inverted, **stacks,
             slides_ok=background.slides_ok, inverted_ok=background.inverted_ok,
             live=json.dumps(dict(slide_hours=background.slide_hours,
                                  data_hours=background.data_hours, scale=background.scale,
                                  tail_from=background.tail_from, floor=background.floor,
                                  slide_floor=background.slide_floor,
                                  stack_slide_hours=background.stack_slide_hours,
                                  stamp=stamp)))


def load_background(path) -> tuple:
    """``(Background, stamp)`` saved by :func:`save_background`."""
    saved = np.load(path)
    live = json.loads(str(saved["live"]))
    stamp = live.pop("stamp")
    optional = {k: saved[k] for k in ("stacks", "stack_slides", "slides_ok", "inverted_ok")
                if k in saved.files}
    return Background(saved["slides"], inverted=saved["inverted"], **optional, **live), stamp


def background_done(folder, stamp) -> bool:
    path = Path(folder) / "background.npz"
    return path.exists() and load_background(path)[1] == stamp


def background_tables(folders: dict):
    """``(maxima, live)``: every group's background maxima (``band``, ``kind``: slides,
    inverted, stacks or stack_slides, ``z``, ``consistent``: it passes the chi-squared test) and live
    times (:data:`LIVE_COLUMNS`), for the groups that have one."""
    maxima, live = [], []
    for group, folder in folders.items():
        path = Path(folder) / "background.npz"
        if not path.exists():
            continue
        b, _ = load_background(path)
        stacks = () if b.stacks is None else b.stacks
        stack_slides = () if b.stack_slides is None else b.stack_slides
        for kind, z, ok in (("slides", b.slides, b.slides_ok),
                            ("inverted", b.inverted, b.inverted_ok),
                            ("stacks", stacks, np.ones(len(stacks), bool)),
                            ("stack_slides", stack_slides, np.ones(len(stack_slides), bool))):
            maxima += [(group.band, kind, float(v), bool(k)) for v, k in zip(z, ok)]
        live.append((group.band, group.obs_id, group.wafer, b.slide_hours, b.data_hours,
                     b.scale, np.nan if b.tail_from is None else b.tail_from, b.floor,
                     b.slide_floor, b.stacks is not None, b.stack_slide_hours))
    maxima = Table(rows=maxima or None, names=("band", "kind", "z", "consistent"),
                   dtype=(str, str, float, bool))
    live = Table(rows=live or None, names=LIVE_COLUMNS,
                 dtype=(str, str, str, float, float, float, float, float, float, bool,
                        float))
    for name in ("slide_hours", "data_hours", "stack_slide_hours"):
        live[name].unit = u.hour
    return maxima, live


def pooled_backgrounds(maxima: Table, live: Table) -> dict:
    """``{band: Background}`` pooled over the band's groups."""
    out = {}
    for band in sorted(set(np.asarray(live["band"]).astype(str))):
        rows = live[live["band"] == band]
        mine = maxima[maxima["band"] == band]
        tail = float(rows["tail_from"][0])
        ok = (np.asarray(mine["consistent"], bool) if "consistent" in mine.colnames
              else np.ones(len(mine), bool))
        slides, inverted = mine["kind"] == "slides", mine["kind"] == "inverted"
        stacked = "stacked" in rows.colnames and np.any(rows["stacked"])
        slid = stacked and "stack_slide_hours" in rows.colnames
        out[band] = Background(
            np.asarray(mine["z"][slides], float), float(np.sum(rows["slide_hours"])),
            np.asarray(mine["z"][inverted], float), float(np.sum(rows["data_hours"])),
            ok[slides], ok[inverted], np.nan,
            None if not np.isfinite(tail) else tail, float(rows["floor"][0]),
            float(np.max(rows["slide_floor"])) if "slide_floor" in rows.colnames else None,
            np.asarray(mine["z"][mine["kind"] == "stacks"], float) if stacked else None,
            np.asarray(mine["z"][mine["kind"] == "stack_slides"], float) if slid else None,
            float(np.sum(rows["stack_slide_hours"])) if slid else 0.0)
    return out


def live_statistics(live: Table) -> dict:
    """``{band: the statistic its campaign ranked detections by}`` from ``far_live`` (its
    ``statistic`` column; ``map_z`` where none is named: coherent-mode results written before
    paper-mode budgets). Combined campaigns may differ band by band."""
    names = (np.ma.filled(np.ma.asarray(live["statistic"]), "") if "statistic" in live.colnames
             else np.full(len(live), ""))
    out = {}
    for band, name in zip(np.asarray(live["band"]).astype(str), names):
        out.setdefault(band, str(name) or "map_z")
    return out


def band_statistic(table: Table, band_key: str, statistics: dict) -> np.ndarray:
    """Each row's value of its band's statistic (``statistics``: :func:`live_statistics`;
    ``band_key``: the band column), NaN where the column is missing or masked."""
    out = np.full(len(table), np.nan)
    if not len(table):
        return out
    bands = np.asarray(table[band_key]).astype(str)
    for band, name in statistics.items():
        sel = bands == band
        if name in table.colnames and sel.any():
            out[sel] = np.ma.filled(np.ma.asarray(table[name][sel], float), np.nan)
    return out


def budget_table(backgrounds: dict, fitted_noise: Table, wafer_hours: dict,
                 statistics: dict | None = None) -> Table:
    """Per band: the Z at the paper's rate (``z_budget``; with sweep stacking half the rate
    each for single crossings and for stacks, ``z_stack_budget``), the background behind it,
    and the noise-only detections whose statistic (``statistics``: {band: column}, default
    ``map_z``) reaches their budget (measured rate per wafer-band-hour beside the target)."""
    statistics = statistics or {band: "map_z" for band in backgrounds}
    budgets = band_budgets(backgrounds)
    above = budget_margin(fitted_noise, "band", statistics, budgets) >= 0
    rows = []
    for band, b in backgrounds.items():
        target = PAPER_RATE_PER_WBH.get(band, np.nan)
        z, z_stack, z_failing = budgets[band]
        mine = np.asarray(fitted_noise["band"]).astype(str) == band
        found = np.asarray(fitted_noise["detected"], bool)[mine] & above[mine]
        hours = wafer_hours.get(band, np.nan)
        n = int(found.sum())
        rows.append((band, statistics[band], target, z, z_stack, z_failing, b.slide_hours,
                     b.data_hours,
                     len(b.slides), len(b.inverted), 0 if b.stacks is None else len(b.stacks),
                     hours, n, n / hours, np.sqrt(max(n, 1)) / hours, target * hours))
    table = Table(rows=rows or None,
                  names=("band", "statistic", "target_per_wbh", "z_budget", "z_stack_budget",
                         "z_budget_chi2_failed", "slide_hours", "data_hours", "n_slide_maxima",
                         "n_inverted_maxima",
                         "n_stack_maxima", "wafer_hours", "n_noise_above", "noise_rate",
                         "noise_rate_err", "expected_above"),
                  dtype=("U8", "U16", float, float, float, float, float, float, int, int, int,
                         float, int, float, float, float))
    for name in ("slide_hours", "data_hours", "wafer_hours"):
        table[name].unit = u.hour
    for name in ("target_per_wbh", "noise_rate", "noise_rate_err"):
        table[name].unit = 1 / u.hour
    return table


def band_budgets(backgrounds: dict) -> dict:
    """``{band: (z_budget, z_stack_budget, z_budget_chi2_failed)}``: the lowest Z of a single
    crossing and of a sweep stack (NaN without stacking) within the paper's rate, split in
    halves between the two when the band's search stacks, and of a single crossing that
    fails the chi-squared test (ranked among every background maximum, not only those that
    pass it)."""
    out = {}
    for band, b in backgrounds.items():
        target = PAPER_RATE_PER_WBH.get(band, np.nan)
        rate = target / 2 if b.stacks is not None else target
        z = b.threshold(rate) if np.isfinite(rate) else np.nan
        z_stack = b.threshold(rate, stacked=True) if b.stacks is not None and \
            np.isfinite(rate) else np.nan
        z_failing = b.threshold(rate, consistent=False) if np.isfinite(rate) else np.nan
        if np.isfinite(target) and not np.isfinite(z):
            log.warning("%s: %.1f h of slides and %.2f h of inverted data cannot resolve the "
                        "paper's rate of %.3f per wafer-band-hour: no thresholds at a "
                        "false-alarm budget (more noise-only hours or n_slides)", band,
                        b.slide_hours, b.data_hours, target)
        out[band] = (z, z_stack, z_failing)
    return out


def budget_margin(table: Table, band_key: str, statistics: dict, budgets: dict) -> np.ndarray:
    """Each row's statistic (:func:`band_statistic`) less its budget (:func:`band_budgets`:
    a sweep stack's, ``n_crossings`` > 1, or a single crossing's, by whether it passes the
    chi-squared test, ``coherent_consistent``): >= 0 is within the false-alarm budget (NaN:
    no statistic or no budget)."""
    margin = band_statistic(table, band_key, statistics)
    if not len(table):
        return margin
    bands = np.asarray(table[band_key]).astype(str)
    stacked = (np.ma.filled(np.ma.asarray(table["n_crossings"], float), 1.0) > 1
               if "n_crossings" in table.colnames else np.zeros(len(table), bool))
    consistent = _consistent(table)
    for i, band in enumerate(bands):
        z, z_stack, z_failing = budgets.get(band, (np.nan,) * 3)
        margin[i] -= z_stack if stacked[i] else z if consistent[i] else z_failing
    return margin


def _consistent(table: Table) -> np.ndarray:
    """Each row's ``coherent_consistent`` (True where missing or masked)."""
    if "coherent_consistent" not in table.colnames:
        return np.ones(len(table), bool)
    return np.ma.filled(np.ma.asarray(table["coherent_consistent"], bool), True)


def noise_far(backgrounds: dict, fitted_noise: Table, statistics: dict | None = None
              ) -> Table:
    """The noise-only detections with their statistic ``z`` (``statistics`` as for
    :func:`budget_table`) and the ``far`` it has (a sweep stack's from the stacks'
    background; calibration: the number with ``far <= x`` should be ``x`` times the
    wafer-band-hours)."""
    statistics = statistics or {band: "map_z" for band in backgrounds}
    keep = (np.asarray(fitted_noise["detected"], bool)
            & np.isin(np.asarray(fitted_noise["band"]).astype(str), list(backgrounds))
            if len(fitted_noise) else np.zeros(0, bool))
    bands = np.asarray(fitted_noise["band"]).astype(str)[keep] if keep.any() else []
    out = Table({"band": np.asarray(bands, "U8"),
                 "z": band_statistic(fitted_noise, "band", statistics)[keep]})
    stacked = (np.ma.filled(np.ma.asarray(fitted_noise["n_crossings"], float), 1.0)[keep] > 1
               if "n_crossings" in fitted_noise.colnames else np.zeros(len(out), bool))
    far = np.full(len(out), np.nan)
    for band, b in backgrounds.items():
        sel = np.asarray(out["band"]).astype(str) == band
        z = np.asarray(out["z"], float)
        single = sel & ~stacked
        far[single] = b.far(z[single], _consistent(fitted_noise)[keep][single])["far"]
        far[sel & stacked] = b.stack_far(z[sel & stacked])["far"]
    out["far"] = far * (1 / u.hour)
    return out


def search_background(group, folder, search_steps, settings: dict, stamp):
    """Compute and save the background of one prepared group (``settings``:
    ``transient_significance``'s, as a dict); run in a worker like the false-positive
    search."""
    from so_transients.campaign.noise import GroupState
    state = GroupState.load(group, folder, search_steps)
    background = group_background(state, search_steps, SignificanceConfig(**settings))
    save_background(background, Path(folder) / "background.npz", stamp)
