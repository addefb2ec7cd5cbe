"""Real wafers drawn at random, through both shipped site configs: flares found, their fluxes
and positions, and detections in the wrong place, per realization.

    python studies/drawn_wafers.py                         # realizations 1-20, 6 minutes each
    python studies/drawn_wafers.py --seeds 3 7 --keep data/drawn
    python studies/drawn_wafers.py --noise-only --minutes 30

Each realization draws which imperfections occur and how strong they are
(:func:`so_transients.campaign.drawn_wafer.drawn_config`: dead channels that keep their
readout's jumps and cosmic rays, jumps of +-1-10 Jy several per detector, noise and gain
scatter, time constants with det_cal errors and NaN tau_eff, NaN detectors and stretches,
focal-plane errors, cosmic rays on 5-40 detectors at once), and the simulator draws on which
channels, independently. Ten 3 Jy and five 900 mJy flares (t_r = 10 s) peak as they cross
random detectors. ``configs/preprocess_production.yaml`` and ``configs/preprocess_paper.yaml``
run, as shipped, through sotodlib's site pipeline. Per realization and config: bright
flares found, how many within 10 % of their flux and 0.2' of their position, the worst flux
ratio and offset, detections no flare explains, and ``mislocated``: detections with fitted
S/N >= 10 more than 0.5' from every flare. Writes ``drawn_wafers.ecsv`` (one row per
realization and config, with what was drawn) and prints a Markdown table; with
``--noise-only``, false detections per wafer-band-hour instead.
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import numpy as np
from astropy.table import Table

from so_transients.campaign.drawn_wafer import (
    SHIPPED, config_summaries, drawn_config, drawn_summary, realization_rows, run_shipped
)
from so_transients.campaign.provenance import stamp
from so_transients.campaign.real_wafer import (
    flare_list, mislocated, score, simulate_seed, summary
)
from so_transients.site.losses import group_losses


def realization_row(sim, found, config, duration, noise_only):
    """One realization's figures for one config."""
    health = group_losses(config)[0]
    row = {"n_eff": float(health["n_eff"]), "used": int(health["used"]),
           "health": str(health["health"])}
    if noise_only:
        return {**row, "false": len(found), "hours": duration / 3600}
    rows, unmatched = score(sim, found)
    out = summary(rows, unmatched, duration / 3600)
    bright = [r for r in rows if r["s_peak"] == 3000.0 and r["crossings"]]
    good = [r for r in bright if r["n_det"] and abs(r["flux_ratio"] - 1) <= 0.10
            and r["offset_arcmin"] <= 0.2]
    return {**row, "bright_found": out["bright"]["found"], "bright_crossed": len(bright),
            "bright_good": len(good), "faint_found": out["faint"]["found"],
            "faint_crossed": out["faint"]["crossed"],
            "flux_ratio_worst": out["bright_flux_ratio_worst"],
            "offset_max_arcmin": out["bright_offset_max_arcmin"],
            "unmatched": unmatched, "mislocated": mislocated(sim, found)}


def study_parser(doc, out):
    """The options both realization studies take (``out``: the default table)."""
    p = argparse.ArgumentParser(description=doc.split("\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 21)))
    p.add_argument("--modes", nargs="+", default=["coherent", "paper"])
    p.add_argument("--minutes", type=float, default=6.0)
    p.add_argument("--noise-only", action="store_true")
    p.add_argument("--keep", type=Path, default=None, help="folder to keep the data in")
    p.add_argument("--out", type=Path, default=Path(out))
    return p


def run_study(args, simulate_one, describe):
    """Per seed of ``args``: ``simulate_one(folder, seed)`` (a result with ``context``), both
    shipped configs on it, one row each (``describe(sim, seed)``: the realization's own
    columns, then :func:`realization_row`'s), the table written after every realization;
    prints it as Markdown at the end."""
    duration = args.minutes * 60
    table, out = [], None
    with tempfile.TemporaryDirectory(prefix="wafer_study_") as tmp:
        base = args.keep or Path(tmp)
        for seed in args.seeds:
            sim = simulate_one(base / f"seed{seed}", seed)
            for mode in args.modes:
                found, config = run_shipped(sim, base / f"seed{seed}_runs", mode)
                row = {"seed": seed, "config": SHIPPED[mode].name, **describe(sim, seed),
                       **realization_row(sim, found, config, duration, args.noise_only)}
                table.append(row)
                print(row, flush=True)
            if not args.keep:
                for path in sorted(base.glob(f"seed{seed}*")):
                    shutil.rmtree(path, ignore_errors=True)
            out = write_table(table, args)      # after every realization: a partial run counts
    print_markdown(out, args.noise_only)


def main(argv=None):
    args = study_parser(__doc__, "drawn_wafers.ecsv").parse_args(argv)
    duration = args.minutes * 60

    def simulate_one(folder, seed):
        flares = [] if args.noise_only else flare_list(seed, duration)
        return simulate_seed(folder, seed, duration, flares, drawn_config(seed))

    run_study(args, simulate_one, lambda sim, seed: drawn_summary(drawn_config(seed)))


def write_table(table, args):
    """The rows so far as an ECSV table at ``args.out``."""
    names = list(dict.fromkeys(k for r in table for k in r))
    out = Table(rows=[[r.get(k, np.nan) for k in names] for r in table], names=names)
    out.meta["comments"] = [f"{Path(sys.argv[0]).name}, seeds {args.seeds}, modes {args.modes}",
                            f"{args.minutes:g} minutes of one f090 wafer-band per realization",
                            f"{stamp()}; configs as shipped at that commit"]
    out.write(args.out, overwrite=True)
    return out


def print_markdown(out, noise_only):
    if noise_only:
        for config in sorted(set(out["config"])):
            rows = out[out["config"] == config]
            hours = float(np.sum(rows["hours"]))
            print(f"{config}: {int(np.sum(rows['false']))} false detections in {hours:.2f} "
                  f"wafer-band-hours")
        return
    print("| config | realizations | 3 Jy found | within 10 % and 0.2' | worst flux ratio | "
          "largest offset (') | 900 mJy found | unmatched | mislocated |")
    print("| --- " * 9 + "|")
    for row in config_summaries(out):
        print("| " + " | ".join(row) + " |")
    print()
    print("| seed | config | 3 Jy found | within 10 %, 0.2' | worst flux ratio | max offset (') "
          "| 900 mJy | unmatched | mislocated | n_eff / used |")
    print("| --- " * 10 + "|")
    for row in realization_rows(out):
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
