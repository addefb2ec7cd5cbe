"""What each detector imperfection costs: the quick campaign with one imperfection at a time.

    python studies/imperfection_campaigns.py [--out data/imperfections] [--only NAME ...]

For ``none``, every section of ``configs/sim_realistic.yaml`` alone, and ``all``, runs
``studies/configs/campaign_quick_realistic.yaml`` (f090, t_r 0.5 and 5 s, 150-1200 mJy, 20 flares a
cell, 10 minutes of one wafer, ``studies/configs/preprocess_paper_realistic.yaml``) with only that
simulation section switched on, then prints one row per case: efficiency at 300 and 600 mJy
(summed over both t_r), the 50 % and 90 % thresholds at t_r = 5 s, and the noise-only and
sign-inverted false detections per wafer-band-hour. Campaigns already done in ``--out`` are
reused. About 2-3 minutes per case on 2 cores.
"""
import argparse
import copy
import sys
from pathlib import Path

import numpy as np
import yaml
from astropy.table import Table

from so_transients.campaign.config import load_campaign
from so_transients.campaign.run import run_campaign
from so_transients.common.parallel import executor
from so_transients.preprocess.sotodlib_steps import sotodlib_name

ROOT = Path(__file__).resolve().parent.parent
BASE = ROOT / "studies" / "configs" / "campaign_quick_realistic.yaml"
IMPERFECTIONS = ("detector_yield", "noise", "calibration", "time_constants",
                 "focal_plane_errors", "jumps", "glitches")


def case_config(name, out):
    """The base campaign config with only ``name``'s imperfection (``none``, ``all``)."""
    with open(BASE) as f:
        cfg = yaml.safe_load(f)
    sim = cfg["simulation"]
    keep = set(IMPERFECTIONS) if name == "all" else {name}
    for section in IMPERFECTIONS:
        if section not in keep:
            sim.pop(section, None)
    if "glitches" not in keep:
        sim["glitches"] = {"enabled": False}
    cfg["output"] = str(Path(out) / name)
    cfg["full_check"] = {"cells": []}
    path = Path(out) / f"{name}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    cfg["preprocess"] = str(preprocess_config(ROOT / cfg["preprocess"], out,
                                              deconvolve="time_constants" in keep))
    path.write_text(yaml.safe_dump(copy.deepcopy(cfg), sort_keys=False))
    return path


def preprocess_config(path, out, deconvolve):
    """``path``, or without its time-constant deconvolution when the simulation gives the
    detectors none (there is then no det_cal.tau_eff to read)."""
    if deconvolve:
        return path
    with open(path) as f:
        cfg = yaml.safe_load(f)
    cfg["process_pipe"] = [s for s in cfg["process_pipe"] if not (
        sotodlib_name(s["name"]) == "fourier_filter"
        and (s.get("process") or {}).get("filt_function") == "timeconst_filter")]
    derived = Path(out) / "preprocess_no_timeconst.yaml"
    derived.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return derived


def summary(results: Path):
    eff = Table.read(results / "efficiency.ecsv")
    limits = Table.read(results / "thresholds.ecsv")
    false = Table.read(results / "false_positives.ecsv")[0]
    at = {s: eff[eff["s_peak"] == s] for s in (300.0, 600.0)}
    slow = limits[limits["t_rise"] == 5.0][0]
    return {f"eff_{int(s)}": f"{int(t['detected'].sum())}/{int(t['injected'].sum())}"
            for s, t in at.items()} | {
        "s50_5s": f"{slow['s50']:.0f}", "s90_5s": f"{slow['s90']:.0f}",
        "false_noise_per_wbh": f"{false['rate_noise_per_wbh']:.1f}",
        "false_inverted_per_wbh": f"{false['rate_inverted_per_wbh']:.1f}"}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="data/imperfections")
    parser.add_argument("--only", nargs="*", help="cases to run (default: all of them)")
    args = parser.parse_args(argv)
    cases = args.only or ["none", *IMPERFECTIONS, "all"]
    rows = []
    for name in cases:
        cfg = load_campaign(case_config(name, args.out))
        pool, as_completed = executor(cfg.nproc)
        try:
            results = run_campaign(cfg, progress=sys.stderr.isatty(), pool=pool,
                                   as_completed=as_completed,
                                   command="python studies/imperfection_campaigns.py --only "
                                           f"{name}")
        finally:
            if pool is not None:
                pool.shutdown()
        rows.append({"case": name, **summary(results)})
        print(rows[-1], flush=True)
    keys = list(rows[0])
    print("\n| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for row in rows:
        print("| " + " | ".join(str(row[k]) for k in keys) + " |")
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())
