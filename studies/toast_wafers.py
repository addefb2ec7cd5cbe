"""TOD from TOAST 3 (a simulator this package did not write) through both shipped site configs:
flares found, fluxes, positions and detections in the wrong place, per realization.

    pip install toast                                # TOAST 3 from the package index
    python studies/toast_wafers.py                   # realizations 1-20, ideal detectors ...
    python studies/toast_wafers.py --imperfect       # ... or those of a drawn real wafer
    python studies/toast_wafers.py --noise-only --seeds 1 2 3 --minutes 20

Each realization is one TOAST observation (:mod:`so_transients.sim.toast_tod`: a 331-pixel
hexagonal f090 wafer, a ground scan at the SO site between azimuths 140 and 160 degrees at
elevation 50, TOAST's noise and atmosphere) with ten 3 Jy and five 900 mJy flares injected
at TOAST's own pointing; ``--imperfect`` adds the imperfections of
:func:`so_transients.campaign.drawn_wafer.drawn_config` drawn for the same seed. Both
shipped configs run through sotodlib's site pipeline. Writes ``toast_wafers.ecsv`` after
each realization (one row per realization and config) and prints a Markdown table.
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

from so_transients.campaign.drawn_wafer import SHIPPED, drawn_config, run_shipped
from so_transients.sim.toast_tod import ToastSetup, simulate_toast

from drawn_wafers import print_markdown, realization_row, write_table   # noqa: E402

IMPERFECTIONS = ("noise", "detector_yield", "calibration", "time_constants",
                 "focal_plane_errors", "jumps", "gaps", "glitches")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 21)))
    p.add_argument("--modes", nargs="+", default=["coherent", "paper"])
    p.add_argument("--minutes", type=float, default=6.0)
    p.add_argument("--imperfect", action="store_true",
                   help="add a drawn real wafer's imperfections")
    p.add_argument("--noise-only", action="store_true")
    p.add_argument("--keep", type=Path, default=None)
    p.add_argument("--out", type=Path, default=Path("toast_wafers.ecsv"))
    args = p.parse_args(argv)
    duration = args.minutes * 60
    table = []
    with tempfile.TemporaryDirectory(prefix="toast_wafers_") as tmp:
        base = args.keep or Path(tmp)
        for seed in args.seeds:
            cfg = drawn_config(seed)
            setup = ToastSetup(duration=duration, imperfections={
                k: cfg[k] for k in IMPERFECTIONS} if args.imperfect else {})
            sim = simulate_toast(base / f"seed{seed}", seed, setup, flares=not args.noise_only)
            for mode in args.modes:
                found, config = run_shipped(sim, base / f"seed{seed}_runs", mode)
                row = {"seed": seed, "config": SHIPPED[mode].name,
                       "imperfect": args.imperfect, "pointing_arcsec": sim.pointing_arcsec,
                       **realization_row(sim, found, config, duration, args.noise_only)}
                table.append(row)
                print(row, flush=True)
            if not args.keep:
                for path in sorted(base.glob(f"seed{seed}*")):
                    shutil.rmtree(path, ignore_errors=True)
            out = write_table(table, args)
    print_markdown(out, args.noise_only)


if __name__ == "__main__":
    main()
