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

import os

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

from so_transients.campaign.drawn_wafer import drawn_config
from so_transients.sim.toast_tod import ToastSetup, simulate_toast

from drawn_wafers import run_study, study_parser   # noqa: E402

IMPERFECTIONS = ("noise", "detector_yield", "calibration", "time_constants",
                 "focal_plane_errors", "jumps", "gaps", "glitches")


def main(argv=None):
    p = study_parser(__doc__, "toast_wafers.ecsv")
    p.add_argument("--imperfect", action="store_true",
                   help="add a drawn real wafer's imperfections")
    args = p.parse_args(argv)

    def simulate_one(folder, seed):
        cfg = drawn_config(seed)
        setup = ToastSetup(duration=args.minutes * 60, imperfections={
            k: cfg[k] for k in IMPERFECTIONS} if args.imperfect else {})
        return simulate_toast(folder, seed, setup, flares=not args.noise_only)

    run_study(args, simulate_one, lambda sim, seed: {"imperfect": args.imperfect,
                                                     "pointing_arcsec": sim.pointing_arcsec})


if __name__ == "__main__":
    main()
