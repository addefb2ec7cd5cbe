"""A real wafer, every imperfection at once: simulate it with flares, run the site pipeline in
either search mode, and score the detections against the truth (``studies/real_wafer.py``;
the tests of ``tests/site/test_real_wafer.py``).

The simulation is ``studies/configs/real_wafer.yaml`` (one MF wafer at f090, every
imperfection drawn independently on every channel) with flares of ``t_r`` = 10 s peaking as
they cross detectors drawn at random (so that the flux is S_p throughout a crossing). Paper
mode runs ``studies/configs/preprocess_paper_realistic.yaml``; coherent mode the same standard steps with
``transient_find`` in coherent mode and ``transient_significance``. Detections are matched to
the truth within 3 s and 3', wider than any error the search should make, so that what is
asserted about offsets and times can fail. :func:`false_detections` lists the detections no
flare explains beside the cosmic rays, jumps and NaN stretches near them in the truth.
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import yaml
from astropy.table import Table
from sotodlib import core

from so_transients.campaign.matching import group_crossings, match
from so_transients.campaign.search_steps import before_fit
from so_transients.common.angles import ARCMIN
from so_transients.common.bands import get_band
from so_transients.common.flare_model import flare_flux
from so_transients.site.pipeline import (
    archive_index, failed_groups, run_site_pipeline, write_site_config
)
from so_transients.io.tod_file import read_tod
from so_transients.preprocess.slot_storage import unpack
from so_transients.site.results import archive_entries, archive_table
from so_transients.sim.config import SimConfig
from so_transients.sim.focal_plane import tube_detectors
from so_transients.sim.simulate import simulate

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "studies" / "configs" / "real_wafer.yaml"
PAPER = ROOT / "studies" / "configs" / "preprocess_paper_realistic.yaml"
BRIGHT, FAINT = 3000.0, 900.0
MATCH_DT, MATCH_OFFSET = 3.0, 3.0 * ARCMIN


def coherent_pipe(paper_pipe, max_far):
    """The paper-mode pipe with transient_find in coherent mode and transient_significance
    (100 slides in 4 groups, ``max_far``) before transient_fit."""
    pipe = [dict(s) for s in paper_pipe]
    for step in pipe:
        if step["name"] == "transient_find":
            step["calc"] = {**step["calc"], "mode": "coherent"}
    return before_fit(pipe, {"name": "transient_significance",
                             "calc": {"n_slides": 100, "slide_groups": 4, "max_far": max_far},
                             "save": True})


def flare_list(seed, duration, n_bright=10, n_faint=5, t_rise=10.0):
    """Flares peaking as they cross random w16 f090 detectors, at least 20 s apart."""
    rng = np.random.default_rng(1000 + seed)
    dets = tube_detectors("i1")
    names = [n for n, w, b in zip(dets["det_id"], dets["wafer_slot"], dets["bandpass"])
             if w == "w16" and b == "f090"]
    n = n_bright + n_faint
    slots = np.arange(20.0, duration - 20.0, 20.0)
    times = np.sort(rng.choice(slots, n, replace=False) + rng.uniform(0, 5, n))
    fluxes = rng.permutation([BRIGHT] * n_bright + [FAINT] * n_faint)
    return [{"at_detector": str(d), "at_time": float(t), "t_peak": float(t),
             "s_peak_mjy": float(s), "t_rise": t_rise}
            for d, t, s in zip(rng.choice(names, n, replace=False), times, fluxes)]


def simulate_seed(root, seed, duration, flares, config=CONFIG):
    """``config`` (a file, the real wafer by default, or a config dict) simulated for
    ``duration`` s with ``flares``."""
    cfg = (copy.deepcopy(config) if isinstance(config, dict)
           else yaml.safe_load(Path(config).read_text()))
    cfg["observation"]["duration"] = duration
    cfg.update(seed=seed, output=str(root), flares={"list": flares})
    return simulate(SimConfig.from_dict(cfg), progress=False)


def run_mode(sim, root, mode, max_far, template=PAPER, every=False):
    """The site pipeline in ``mode`` on ``sim`` (paper mode: the site config ``template``; coherent
    mode: its standard steps); the archive's detections, with ``peak_readout`` (the readout id
    of each one's highest-S/N detector) and in ``meta["error_scale"]`` the fit's error scales
    measured in the groups (:func:`read_detections`); with ``every``, every candidate
    (:func:`read_candidates`)."""
    config = write_site_config(sim.context.parent, path=root / f"{mode}.yaml", template=template,
                               results=root / mode)
    if mode == "coherent":
        cfg = yaml.safe_load(config.read_text())
        cfg["process_pipe"] = coherent_pipe(cfg["process_pipe"], max_far)
        config.write_text(yaml.safe_dump(cfg, sort_keys=False))
    run_site_pipeline(config, nproc=1)
    failed = failed_groups(config)
    if failed:
        raise RuntimeError(f"{config}: failed groups:\n{failed}")
    return read_candidates(config) if every else read_detections(config)


def read_candidates(config):
    """Every candidate in the archive of site config ``config``, with in
    ``meta["error_scale"]`` the fit's error scales measured in the groups."""
    every = archive_table(config, detected_only=False)
    scales = np.asarray(every["error_scale"], float)
    every.meta["error_scale"] = sorted(set(scales[np.isfinite(scales)].round(4).tolist()))
    return every


def read_detections(config):
    """The detections in the archive of site config ``config``, with ``peak_readout`` (the
    readout id of each one's highest-S/N detector) and in ``meta["error_scale"]`` the fit's
    error scales measured in the groups."""
    every = read_candidates(config)
    found = every[np.asarray(every["detected"], bool)]
    peaks = {}
    for obs_id, tags, filename, dataset in archive_entries(archive_index(config)):
        part = unpack(core.AxisManager.load(filename, dataset)["transient_find"],
                      fields=["cand_id"])
        peaks.update({(obs_id, tags.get("wafer_slot"), int(c)): str(d)
                      for c, d in zip(part["cand_id"], part["det"])})
    found["peak_readout"] = [peaks[(r["obs_id"], r["wafer_slot"], int(r["cand_id"]))]
                             for r in found] if len(found) else np.zeros(0, str)
    return found


def score(sim, found):
    """Per flare: found, detections of its crossings, and of the detection where it is
    brightest, the flux over the flare's at that time and the offset; unmatched count."""
    flares = Table.read(sim.context.parent / "truth" / "flares.ecsv")
    fwhm = {b: get_band(b).fwhm for b in set(flares["band"])}
    crossings = group_crossings(sim.context, flares, fwhm)
    matched = match(found, flares, crossings, max_dt=MATCH_DT, max_offset=MATCH_OFFSET)
    rows = []
    for fl in flares:
        mine = matched[matched["source_id"] == fl["source_id"]]
        n_cross = sum(len(v) for k, v in crossings.items() if k[0] == fl["source_id"])
        true = flare_flux(np.asarray(mine["t_peak"], float), fl["t_peak"], fl["s_peak"],
                          fl["t_rise"], fl["t_decay"], fl["eta_rise"], fl["eta_decay"])
        best = int(np.argmax(true)) if len(mine) else None
        rows.append({"s_peak": float(fl["s_peak"]), "crossings": n_cross, "n_det": len(mine),
                     "flux_ratio": float(mine["flux"][best] / true[best])
                     if best is not None else np.nan,
                     "offset_arcmin": float(mine["offset"][best] / ARCMIN)
                     if best is not None else np.nan})
    return rows, int(np.sum(matched["source_id"] < 0))


def mislocated(sim, found, min_snr=10.0, max_offset=0.5 * ARCMIN):
    """Detections of ``found`` with ``snr_fit >= min_snr`` that lie more than ``max_offset``
    (rad) from every injected flare crossing them (a confident detection in the wrong
    place)."""
    flares = Table.read(sim.context.parent / "truth" / "flares.ecsv")
    bright = np.nan_to_num(np.asarray(found["snr_fit"], float)) >= min_snr
    if not len(flares):
        return int(bright.sum())
    fwhm = {b: get_band(b).fwhm for b in set(flares["band"])}
    matched = match(found, flares, group_crossings(sim.context, flares, fwhm),
                    max_dt=MATCH_DT, max_offset=max_offset)
    return int(np.sum(bright & (np.asarray(matched["source_id"]) < 0)))


def summary(rows, unmatched, hours):
    def of(flux):
        sel = [r for r in rows if r["s_peak"] == flux and r["crossings"]]
        found = [r for r in sel if r["n_det"]]
        return sel, found
    out = {}
    for name, flux in (("bright", BRIGHT), ("faint", FAINT)):
        sel, found = of(flux)
        out[name] = {"found": len(found), "crossed": len(sel),
                     "twice": sum(r["n_det"] > r["crossings"] for r in found)}
    _, bright = of(BRIGHT)
    ratios = np.array([r["flux_ratio"] for r in bright])
    offsets = np.array([r["offset_arcmin"] for r in bright])
    out["bright_flux_ratio_median"] = float(np.median(ratios)) if len(ratios) else np.nan
    out["bright_flux_ratio_worst"] = float(ratios[np.argmax(np.abs(ratios - 1))]) \
        if len(ratios) else np.nan
    out["bright_offset_max_arcmin"] = float(offsets.max()) if len(offsets) else np.nan
    out["unmatched"] = unmatched
    out["unmatched_per_hour"] = unmatched / hours
    return out


def _nearest(times, at):
    """Signed time from the nearest of ``times`` to each of ``at`` (NaN if there are none)."""
    times = np.asarray(times, float)
    if not len(times):
        return np.full(len(at), np.nan)
    dt = np.asarray(at, float)[:, None] - times[None, :]
    return dt[np.arange(len(at)), np.argmin(np.abs(dt), axis=1)]


def false_detections(sim, found) -> Table:
    """The detections of ``found`` (from :func:`run_mode`) that no flare explains, each with
    what the truth holds near it.

    Columns: the candidate's own (``t_peak``, ``snr_max``, ``snr_fit``, ``n_dets``,
    ``n_fit_dets``, ``flux``, ``chi2_red``, ``peak_readout``), ``peak_ratio`` (snr_max over
    snr_fit), ``t_obs`` (s since the observation's start), the peak detector's ``peak_status``
    and ``peak_noise`` (noise factor) from the truth, ``dt_glitch`` (s from the wafer's nearest
    cosmic ray) and ``glitch_on_peak`` (that cosmic ray hit the peak detector), ``dt_jump`` (s
    from the wafer-band's nearest readout jump) and ``dt_peak_jump`` (from the peak detector's
    nearest jump), ``dt_gap`` (s from the wafer-band's nearest NaN stretch, 0 inside one).
    """
    flares = Table.read(sim.context.parent / "truth" / "flares.ecsv")
    rows = found
    if len(flares) and len(found):
        fwhm = {b: get_band(b).fwhm for b in set(flares["band"])}
        crossings = group_crossings(sim.context, flares, fwhm)
        matched = match(found, flares, crossings, max_dt=MATCH_DT, max_offset=MATCH_OFFSET)
        rows = found[np.asarray(matched["source_id"]) < 0]
    keep = ["obs_id", "wafer_slot", "t_peak", "snr_max", "snr_fit", "n_dets", "n_fit_dets",
            "flux", "chi2_red", "peak_readout"]
    out = Table({k: rows[k] for k in keep}) if len(rows) else Table(
        {k: np.zeros(0, str if k in ("obs_id", "wafer_slot", "peak_readout") else float)
         for k in keep})
    t = np.asarray(out["t_peak"], float)
    out["peak_ratio"] = np.asarray(out["snr_max"], float) / np.asarray(out["snr_fit"], float)
    dets = sim.detectors     # empty for ideal detectors
    names = dets["readout_id"] if len(dets) else []
    status = dict(zip(names, dets["status"])) if len(dets) else {}
    noise = dict(zip(names, np.asarray(dets["noise_factor"], float))) if len(dets) else {}
    wafer_of = dict(zip(names, dets["wafer_slot"])) if len(dets) else {}
    out["peak_status"] = [status.get(r, "ok" if not len(dets) else "?")
                          for r in out["peak_readout"]]
    out["peak_noise"] = [noise.get(r, 1.0 if not len(dets) else np.nan)
                         for r in out["peak_readout"]]
    timestamps = {}
    for obs_id in set(out["obs_id"]):
        tod = next((sim.context.parent / "tod" / obs_id).glob("*.h5"))
        timestamps[obs_id] = read_tod(tod, dets=[], no_signal=True)["timestamps"]
    out["t_obs"] = [w - timestamps[o][0] for o, w in zip(out["obs_id"], t)]
    glitches, jumps, gaps = sim.glitches, sim.jumps, sim.gaps
    dt_glitch, on_peak, dt_jump, dt_peak_jump, dt_gap = [], [], [], [], []
    for row, when in zip(out, t):
        wafer = row["wafer_slot"]
        g = glitches[glitches["wafer_slot"] == wafer] if len(glitches) else glitches
        d = _nearest(g["ctime"], [when])[0] if len(g) else np.nan
        dt_glitch.append(d)
        on_peak.append(bool(len(g)) and row["peak_readout"] in str(
            g["readout_ids"][np.argmin(np.abs(np.asarray(g["ctime"], float) - when))]).split(","))
        j = jumps[[wafer_of.get(r) == wafer for r in jumps["readout_id"]]] if len(jumps) else []
        dt_jump.append(_nearest(j["ctime"], [when])[0] if len(j) else np.nan)
        mine = j[j["readout_id"] == row["peak_readout"]] if len(j) else []
        dt_peak_jump.append(_nearest(mine["ctime"], [when])[0] if len(mine) else np.nan)
        s = gaps[[wafer_of.get(r) == wafer for r in gaps["readout_id"]]] if len(gaps) else []
        if len(s):
            begin = np.asarray(s["ctime"], float)
            stamps = timestamps[row["obs_id"]]
            end = stamps[np.minimum(np.asarray(s["sample"]) + np.asarray(s["n_samples"]),
                                    len(stamps) - 1)]
            dist = np.where((when >= begin) & (when <= end), 0.0,
                            np.minimum(np.abs(when - begin), np.abs(when - end)))
            dt_gap.append(float(dist.min()))
        else:
            dt_gap.append(np.nan)
    out["dt_glitch"], out["glitch_on_peak"] = dt_glitch, on_peak
    out["dt_jump"], out["dt_peak_jump"], out["dt_gap"] = dt_jump, dt_peak_jump, dt_gap
    return out
