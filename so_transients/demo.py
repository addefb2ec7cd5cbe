"""The main job (``make demo``): simulate, run the site pipeline, compare with the truth.

1. simulate the default observation (``configs/sim_demo.yaml``: one MF wafer, 10 minutes, a
   handful of bright and faint flares) into a sotodlib dataset;
2. run ``python -m sotodlib.site_pipeline.preprocess_tod`` with the production config
   (``configs/preprocess_production.yaml``: coherent search, false-alarm rates, ``max_far``)
   pointed at it;
3. read every group's detections from the archive, match them to the injected flares
   (0.5 s, 0.5') and print both, with the per-detection plots' location;
4. join the detections into events and measure their light curves by forced photometry
   (``so-transients events``), into ``<dataset>/events``.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from astropy.table import Table
from sotodlib import core

from so_transients.events.command import run_events, summary
from so_transients.events.config import load_events_config
from so_transients.campaign.matching import compare_with_truth
from so_transients.site.results import archive_table, write_table
from so_transients.site.pipeline import (
    archive_index, failed_groups, run_site_pipeline, write_site_config
)
from so_transients.site.steps_record import record_groups


def report(matched: Table, flares: Table, crossings: dict, t0: float) -> str:
    """Detections in time order, with their candidate ids, next to the injected flares; times
    relative to ``t0`` (ctime)."""
    lines = ["", "Detections (t relative to the observation start):",
             f"  {'cand_id':>7} {'band':5} {'t (s)':>8} {'flux (mJy)':>16} {'S/N':>6} "
             f"{'dets':>5}  {'matched flare':>14} {'dt (s)':>7} {'offset (arcsec)':>16}"]
    for d in matched[np.argsort(matched["t_peak"], kind="stable")] if len(matched) else []:
        src = f"#{d['source_id']}" if d["source_id"] >= 0 else "none (false)"
        lines.append(f"  {d['cand_id']:>7} {d['bandpass']:5} {d['t_peak'] - t0:8.2f} "
                     f"{d['flux']:8.0f} ± "
                     f"{d['flux_err']:<5.0f} {d['snr_fit']:6.1f} {d['n_dets']:5d}  {src:>14} "
                     f"{d['dt']:7.2f} {np.degrees(d['offset']) * 3600:16.1f}")
    lines += ["", "Injected flares:",
              f"  {'#':>3} {'band':5} {'t_peak (s)':>10} {'S_p (mJy)':>10} {'t_r (s)':>8} "
              f"{'crossings':>9} {'detected':>9}"]
    for fl in flares:
        n_cross = sum(len(v) for k, v in crossings.items()
                      if k[0] == fl["source_id"] and k[3] == fl["band"])
        found = np.any((matched["source_id"] == fl["source_id"])
                       & (matched["bandpass"] == fl["band"])) if len(matched) else False
        lines.append(f"  {fl['source_id']:>3} {fl['band']:5} {fl['t_peak'] - t0:10.2f} "
                     f"{fl['s_peak']:10.0f} {fl['t_rise']:8.2f} {n_cross:9d} "
                     f"{'yes' if found else 'no':>9}")
    n_false = int(np.sum(matched["source_id"] < 0)) if len(matched) else 0
    lines.append(f"\n{len(matched)} detections, {n_false} not matching any injected flare.")
    return "\n".join(lines)


def run_demo(dataset: Path, nproc=2, progress=True) -> str:
    """Steps 2 to 4 on an existing simulated dataset; returns the printed report."""
    dataset = Path(dataset)
    config = write_site_config(dataset)
    t0 = time.time()
    run_site_pipeline(config, nproc=nproc, extra_args=["--overwrite"])
    record_groups(config, remade=True)      # so that `so-transients run` may reuse them
    elapsed = time.time() - t0
    errors = failed_groups(config)
    if errors:
        raise RuntimeError(f"the site pipeline failed on some groups:\n{errors}")
    detections = archive_table(config)
    detections.sort("t_peak")                       # a catalogue reads in time order
    table_path = archive_index(config).parent / "detections.ecsv"      # where `run` writes it
    write_table(detections, table_path, config=config, overwrite=True)
    matched, flares, crossings = compare_with_truth(dataset, detections)
    start = min(o["start_time"] for o in core.Context(str(dataset / "context.yaml")).obsdb.query())
    text = (f"Site pipeline: {elapsed:.0f} s (config {config}); archive "
            f"{dataset / 'preprocess'}\n" + report(matched, flares, crossings, start)
            + f"\nDetections table: {table_path}; plots under "
              f"{dataset / 'preprocess' / 'plots'}")
    return text + "\n\nEvents (so-transients events):\n" + events_report(config, nproc, progress)


def events_report(config, nproc=2, progress=True) -> str:
    """Step 4: the events, light curves and figures of the site config's archive."""
    cfg = load_events_config(config, {"nproc": nproc})
    return summary(run_events(cfg, progress=progress), cfg.output)


def get_parser(parser=None):
    """``so-transients demo``'s options (built like a sotodlib site-pipeline element)."""
    import argparse

    from so_transients.cli import DEMO_CONFIG

    if parser is None:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", help=f"simulation YAML (default: {DEMO_CONFIG.name})")
    parser.add_argument("-o", "--out", default="data/demo", help="output folder")
    parser.add_argument("--nproc", type=int, default=2, help="site pipeline processes")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    return parser


def main(args) -> int:
    """Simulate the demo's observation into ``args.out``, then :func:`run_demo` on it."""
    from so_transients.cli import DEMO_CONFIG
    from so_transients.sim.command import run_simulation
    from so_transients.site.summary import dataset_summary

    args.config = args.config or DEMO_CONFIG
    args.seed = None
    args.overwrite = True
    result = run_simulation(args)
    print(dataset_summary(result.context))
    print(run_demo(result.context.parent, nproc=args.nproc, progress=not args.quiet))
    return 0
