"""Checking the fast path: the same flares through the full site pipeline.

For each cell listed under ``full_check`` the flares are drawn in the first noise-only
observation, far enough apart in time not to overlap (``separation`` seconds between one's end
and the next one's start), and then:

* **full path**: the observation is simulated again with the same seed and these flares in the
  TOD (the noise streams do not depend on the flares, so the noise is identical), and
  ``python -m sotodlib.site_pipeline.preprocess_tod`` runs the campaign's preprocess config on
  it; detections are read from the archive and matched as in ``make demo``;
* **fast path**: the same flares (the simulated truth table) are injected one at a time into the
  prepared noise-only groups (:mod:`.flare_injection`).

``full_check.ecsv`` gives both efficiencies with 68 % intervals and, since the two paths see the
same flares in the same noise, their paired comparison: the flares only the fast path found
(``fast_only``) and only the full pipeline found (``full_only``), and McNemar's exact
two-sided p-value (``mcnemar_p``: if both paths detect each flare with the same probability,
the discordant flares go either way with probability 1/2). Two independent binomials' z would
ignore the pairing and overstate the agreement.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from astropy.table import Table

from so_transients.common.angles import ARCMIN, DEG
from so_transients.site.results import archive_table
from so_transients.sim.simulate import rng_for, simulate
from so_transients.sim.config import SimConfig
from so_transients.campaign.matching import compare_with_truth
from so_transients.site.pipeline import failed_groups, run_site_pipeline, write_site_config
from so_transients.campaign.flare_injection import draw_cell_flares
from so_transients.campaign.noise import GroupState
from so_transients.campaign.stats import binomial_interval
from so_transients.campaign.work_units import search_flares


def spaced_flares(cell, n, states, rng, separation, placement="detector_at_peak",
                  flare_eta=1.0):
    """Up to ``n`` flares of ``cell`` whose active windows are ``separation`` s apart."""
    pool = draw_cell_flares(cell, 30 * n, states, rng, placement, flare_eta)
    chosen, busy = [], []
    for k in range(len(pool)):
        start = pool["t_peak"][k] - cell.t_rise - separation / 2
        stop = pool["t_peak"][k] + cell.t_rise + separation / 2
        if all(stop < a or start > b for a, b in busy):
            chosen.append(k)
            busy.append((start, stop))
        if len(chosen) == n:
            break
    return pool[sorted(chosen, key=lambda k: pool["t_peak"][k])]


def flare_list(flares, t0):
    """Explicit flare entries of a simulation config (degrees, seconds from ``t0``)."""
    return [dict(ra=float(f["ra"] / DEG), dec=float(f["dec"] / DEG),
                 t_peak=float(f["t_peak"] - t0), s_peak_mjy=float(f["s_peak"]),
                 t_rise=float(f["t_rise"]), t_decay=float(f["t_decay"])) for f in flares]


def site_processes(nproc, group_bytes, available=None) -> int:
    """Site-pipeline processes that fit in memory: each holds one group (about five copies
    of its signal: the TOD, the low-passed copy for PCA, the filter's work and its S/N), so
    at most ``MemAvailable / (5 x group_bytes)`` of them, between 1 and ``nproc``. Two
    processes on hour-long MF groups (2.7 GB of signal each) exhaust 24 GB."""
    if available is None:
        available = _mem_available()
    return int(max(1, min(nproc, available // max(5 * group_bytes, 1))))


def _mem_available() -> int:
    """Bytes of memory available now (``/proc/meminfo``), or a large number where unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 1 << 62


def full_pipeline(cfg, folder: Path, flares, t0, detsets, progress, group_bytes=0):
    """Simulate the flares into the noise-only observation (its ``detsets`` only: the data
    are those of the whole simulation) and run the site pipeline; returns (truth flares,
    per-flare detected by the full path)."""
    sim = {"seed": cfg.seed, **cfg.simulation}
    sim["flares"] = {"list": flare_list(flares, t0)}
    result = simulate(SimConfig.from_dict(sim), output=folder / "sim", overwrite=True,
                      progress=progress, workers=cfg.nproc, detsets=detsets)
    dataset = result.context.parent
    config = write_site_config(dataset, template=cfg.preprocess,
                               overrides=cfg.preprocess_overrides)
    run_site_pipeline(config, nproc=site_processes(cfg.nproc, group_bytes),
                      extra_args=["--overwrite"])
    errors = failed_groups(config)
    if errors:
        raise RuntimeError(f"full check: the site pipeline failed on some groups:\n{errors}")
    matched, truth, _ = compare_with_truth(dataset, archive_table(config))
    shutil.rmtree(dataset / "tod", ignore_errors=True)   # GBs; the archive and truth stay
    found = {(int(m["source_id"]), str(m["bandpass"])) for m in matched if m["source_id"] >= 0}
    return truth, np.array([(int(f["source_id"]), str(f["band"])) in found for f in truth])


def check_cell(cfg, out: Path, folders: dict, cell, progress=True) -> dict:
    folder = out / "full_check" / cell.label
    obs_id = sorted({g.obs_id for g in folders if g.band == cell.band})[0]
    _, search = cfg.pipeline_steps()
    groups = [g for g in folders if g.obs_id == obs_id and g.band == cell.band]
    states = [GroupState.load(g, folders[g], search) for g in groups]
    rng = rng_for(cfg.seed, "full_check", cell.label)
    flares = spaced_flares(cell, cfg.full_check.n_flares, states, rng,
                           cfg.full_check.separation, cfg.injection.placement,
                           cfg.injection.flare_eta)
    truth, full = full_pipeline(cfg, folder, flares, states[0].timestamps[0],
                                sorted({f"{g.wafer}_{g.band}" for g in groups}), progress,
                                max(s.snr.nbytes for s in states))
    mine = np.asarray(truth["band"]) == cell.band
    truth, full = truth[mine], full[mine]
    fast, _ = search_flares(states, truth, cfg.injection, cfg.matching.max_dt,
                            cfg.matching.max_offset_arcmin * ARCMIN)
    fast_hit = np.asarray(fast["detected"], bool)
    n = len(truth)
    k_fast, k_full = int(fast_hit.sum()), int(full.sum())
    e_fast, lo_fast, hi_fast = binomial_interval(k_fast, n)
    e_full, lo_full, hi_full = binomial_interval(k_full, n)
    fast_only, full_only = int(np.sum(fast_hit & ~full)), int(np.sum(full & ~fast_hit))
    return dict(band=cell.band, t_rise=cell.t_rise, s_peak=cell.s_peak, n=n,
                fast_detected=k_fast, full_detected=k_full, fast_eff=float(e_fast),
                fast_lo=float(lo_fast), fast_hi=float(hi_fast), full_eff=float(e_full),
                full_lo=float(lo_full), full_hi=float(hi_full),
                fast_only=fast_only, full_only=full_only,
                mcnemar_p=mcnemar_p(fast_only, full_only))


def mcnemar_p(b, c) -> float:
    """McNemar's exact two-sided p-value of ``b`` and ``c`` discordant pairs (1 when none)."""
    from scipy.stats import binomtest

    return float(binomtest(b, b + c, 0.5).pvalue) if b + c else 1.0


def run_full_check(cfg, out: Path, folders: dict, progress=True) -> Table:
    """One row per ``full_check`` cell (see the module doc); cached per config."""
    path = out / "full_check" / "full_check.ecsv"
    if path.exists():
        table = Table.read(path)
        if table.meta.get("config_digest") == cfg.digest():
            return table
    rows = [check_cell(cfg, out, folders, cell, progress) for cell in cfg.check_cells]
    table = Table(rows=rows)
    table.meta["config_digest"] = cfg.digest()
    path.parent.mkdir(parents=True, exist_ok=True)
    table.write(path, overwrite=True)
    return table

