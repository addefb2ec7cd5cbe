"""Real wafers drawn at random: each realization draws which imperfections occur, how strong
they are and (in the simulator) on which channels, independently, so that they meet on the
same channels in combinations no hand-written config names (``studies/drawn_wafers.py``).

:func:`drawn_config` is the simulation config of one realization: one MF wafer at f090 (the
band the reference paper measures), with

* dead channels (5-20 %) that record zeros, or a little readout noise, and still their
  readout's jumps and cosmic rays; noisy detectors (0-5 %, 3-20 times the noise); 1-5
  channels of NaN throughout and NaN stretches (0-30 an hour);
* log-normal white-noise scatter (10-40 %), each detector's own 1/f knee;
* gain errors (2-10 %), time constants (1-5 ms) with det_cal's ``tau_eff`` off by 0-15 %
  and NaN for 0-2 % of the detectors; focal-plane errors (0-10");
* readout jumps of +-1-10 Jy on 1-20 % of the detectors, 1 to 2-12 each; cosmic rays
  (30-1500 an hour) on 5-40 detectors at once.

:func:`run_shipped` runs a shipped site config (``configs/``), as it is, on the realization;
:func:`config_summaries` sums a study's table per config, as the results page quotes it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from so_transients.campaign.real_wafer import CONFIG, read_detections
from so_transients.site.pipeline import (
    PAPER, PRODUCTION, failed_groups, run_site_pipeline, write_site_config
)

#: The shipped site configs, by search mode
SHIPPED = {"coherent": PRODUCTION, "paper": PAPER}


def drawn_config(seed) -> dict:
    """The simulation config (a dict, ``SimConfig.from_dict``'s input) of realization
    ``seed``: ``studies/configs/real_wafer.yaml``'s instrument and observation with every
    imperfection's strength drawn (see the module docstring); ``meta`` says what was drawn."""
    rng = np.random.default_rng(50_000 + seed)
    u = lambda lo, hi: float(rng.uniform(lo, hi))
    cfg = yaml.safe_load(Path(CONFIG).read_text())
    cfg["noise"] = {"white_scatter": u(0.1, 0.4), "fknee": [0.02, u(0.05, 0.3)], "alpha": 1.0}
    cfg["detector_yield"] = {
        "dead_fraction": u(0.05, 0.2), "dead_mode": "zeros",
        "dead_noise": float(rng.choice([0.0, u(0.001, 0.05)])),
        "noisy_fraction": u(0.0, 0.05), "noisy_factor": u(3.0, 20.0),
        "lost_detectors": int(rng.integers(1, 6))}
    cfg["calibration"] = {"scatter": u(0.02, 0.1), "distribution": "lognormal"}
    cfg["time_constants"] = {"tau_ms": {"f090": [1.0, 5.0], "f150": [1.0, 5.0],
                                        "f220": 0.4, "f280": 0.4},
                             "metadata_error": u(0.0, 0.15), "metadata_nan": u(0.0, 0.02)}
    cfg["focal_plane_errors"] = {"sigma_arcsec": u(0.0, 10.0)}
    cfg["jumps"] = {"fraction": u(0.01, 0.2), "count": [1, int(rng.integers(2, 13))],
                    "rate_per_hour": 0.0, "height": [1000.0, 10000.0], "units": "mjy"}
    cfg["gaps"] = {"rate_per_hour": u(0.0, 30.0), "duration": [1.0, 5.0]}
    cfg["glitches"] = {"enabled": True, "rate_per_hour": float(np.exp(u(np.log(30),
                                                                          np.log(1500)))),
                       "n_dets": [5, 40], "amplitude_mjy": [5000.0, 50000.0],
                       "time_constant": 0.004}
    return cfg


def drawn_summary(cfg) -> dict:
    """The drawn strengths of :func:`drawn_config`, one number each, for the study's table."""
    return {"dead_fraction": cfg["detector_yield"]["dead_fraction"],
            "dead_noise": cfg["detector_yield"]["dead_noise"],
            "noisy_fraction": cfg["detector_yield"]["noisy_fraction"],
            "lost": cfg["detector_yield"]["lost_detectors"],
            "white_scatter": cfg["noise"]["white_scatter"],
            "gain_scatter": cfg["calibration"]["scatter"],
            "tau_eff_error": cfg["time_constants"]["metadata_error"],
            "tau_eff_nan": cfg["time_constants"]["metadata_nan"],
            "focal_plane_arcsec": cfg["focal_plane_errors"]["sigma_arcsec"],
            "jump_fraction": cfg["jumps"]["fraction"], "jumps_max": cfg["jumps"]["count"][1],
            "gaps_per_hour": cfg["gaps"]["rate_per_hour"],
            "cosmic_rays_per_hour": cfg["glitches"]["rate_per_hour"]}


def run_shipped(sim, root, mode):
    """The shipped site config of ``mode`` (:data:`SHIPPED`), unchanged but for its paths, on
    ``sim`` through sotodlib's site pipeline; the archive's detections
    (:func:`so_transients.campaign.real_wafer.read_detections`). A failed group raises,
    naming it."""
    config = write_site_config(sim.context.parent, path=Path(root) / f"{mode}.yaml",
                               template=SHIPPED[mode], results=Path(root) / mode)
    run_site_pipeline(config, nproc=1)
    failed = failed_groups(config)
    if failed:
        raise RuntimeError(f"{config}: failed groups:\n{failed}")
    return read_detections(config), config


def config_summaries(out) -> list:
    """One row of Markdown cells per config of ``out``, over its realizations: 3 Jy flares
    found and placed within 10 % and 0.2', the worst flux ratio and largest offset, 900 mJy
    flares found, unmatched and mislocated detections (the results page quotes these)."""
    rows = []
    for config in sorted(set(out["config"])):
        r = out[out["config"] == config]
        good, crossed = int(np.sum(r["bright_good"])), int(np.sum(r["bright_crossed"]))
        rows.append([str(config), str(len(r)),
                     f"{int(np.sum(r['bright_found']))} / {crossed}",
                     f"{good} ({100 * good / crossed:.1f} %)",
                     f"{np.nanmin(r['flux_ratio_worst']):.3f}",
                     f"{np.nanmax(r['offset_max_arcmin']):.2f}",
                     f"{int(np.sum(r['faint_found']))} / {int(np.sum(r['faint_crossed']))}",
                     str(int(np.sum(r["unmatched"]))), str(int(np.sum(r["mislocated"])))])
    return rows


def realization_rows(out) -> list:
    """One row of Markdown cells per realization and config of ``out`` (the results page's
    per-realization tables): 3 Jy flares found and placed within 10 % and 0.2', the worst
    flux ratio and largest offset, 900 mJy flares found, unmatched and mislocated
    detections, the effective number of detectors against those used."""
    return [[str(r["seed"]), str(r["config"]), f"{r['bright_found']} / {r['bright_crossed']}",
             str(r["bright_good"]), f"{r['flux_ratio_worst']:.3f}",
             f"{r['offset_max_arcmin']:.2f}", f"{r['faint_found']} / {r['faint_crossed']}",
             str(r["unmatched"]), str(r["mislocated"]), f"{r['n_eff']:.0f} / {r['used']}"]
            for r in out]
