"""A real wafer, every imperfection at once: the search's flares, fluxes, positions and false
detections on several simulation seeds, in both search modes.

    python studies/real_wafer.py                      # seeds 1-5, 10 minutes each, both modes
    python studies/real_wafer.py --seeds 1 --modes paper --keep data/real_wafer
    python studies/real_wafer.py --noise-only [--config studies/configs/ideal_wafer.yaml]
    python studies/real_wafer.py --noise-only --modes paper --site-config <site config>

Each seed simulates ``studies/configs/real_wafer.yaml`` (one MF wafer at f090, every
imperfection drawn independently on every channel) with ten 3 Jy and five 900 mJy flares
(t_r = 10 s, so that the flux is S_p throughout a crossing) peaking as they cross detectors
drawn at random, at least 20 s apart. It runs the shipped site config through sotodlib's site
pipeline (paper mode: ``studies/configs/preprocess_paper_realistic.yaml``; coherent mode with
``transient_significance``: the same standard steps) and matches the detections to the truth
within 3 s and 3'. With ``--noise-only`` (and ``--config studies/configs/ideal_wafer.yaml``
for ideal detectors) it counts the false detections per wafer-band-hour instead.
``--site-config`` runs paper mode with another site config (a copy of the shipped one with a
setting changed). Prints its Markdown table (a row per mode and seed) and writes ``real_wafer.json``, and the
detections no flare explains, with the cosmic rays, jumps and NaN stretches near them, to
``real_wafer_false.ecsv`` (beside the JSON), and every mode's results per seed to
``real_wafer_seeds.ecsv``; with ``--noise-only``, paper mode's false
detections per seed to ``real_wafer_noise.ecsv`` (the table the drawn-wafer page's ideal row
reads).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

from astropy.table import Table, vstack

from so_transients.campaign.provenance import commit
from so_transients.campaign.real_wafer_tables import (
    flares_markdown, noise_markdown, seed_table
)
from so_transients.campaign.real_wafer import (
    CONFIG, PAPER, false_detections, flare_list, run_mode, score, simulate_seed, summary
)

FALSE_COLUMNS = ("t_obs", "snr_max", "snr_fit", "peak_ratio", "n_dets", "n_fit_dets", "flux",
                 "peak_status", "dt_glitch", "glitch_on_peak", "dt_jump", "dt_peak_jump", "dt_gap")


def noise_table(seeds: Table, site_config, made_at) -> Table:
    """Paper mode's rows of a noise-only run's :func:`seed_table` as the drawn-wafer page
    reads them: a row per seed with its false detections, wafer-band-hours, the largest error
    scale the fit used, the site config and ``made_at``, the commit that ran."""
    paper = seeds[seeds["mode"] == "paper"]
    table = Table(dict(seed=paper["seed"], config=[Path(site_config).name] * len(paper),
                       false=paper["false"], hours=paper["hours"],
                       error_scale_max=paper["error_scale_max"],
                       commit=[made_at] * len(paper)))
    table.meta["comments"] = list(seeds.meta["comments"])
    return table


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    p.add_argument("--modes", nargs="+", default=["paper", "coherent"])
    p.add_argument("--minutes", type=float, default=10.0, help="of each seed's observation")
    p.add_argument("--config", type=Path, default=CONFIG, help="simulation config")
    p.add_argument("--noise-only", action="store_true",
                   help="no flares: count the false detections per wafer-band-hour")
    p.add_argument("--max-far", type=float, default=0.08)
    p.add_argument("--keep", type=Path, default=None, help="folder to keep the data in")
    p.add_argument("--site-config", type=Path, default=PAPER,
                   help="site config of paper mode (coherent mode uses its standard steps)")
    p.add_argument("--json", type=Path, default=Path("real_wafer.json"))
    args = p.parse_args(argv)
    results = {m: {} for m in args.modes}
    false = []
    duration = args.minutes * 60
    with tempfile.TemporaryDirectory(prefix="real_wafer_") as tmp:
        base = args.keep or Path(tmp)
        for seed in args.seeds:
            flares = [] if args.noise_only else flare_list(seed, duration)
            sim = simulate_seed(base / f"seed{seed}", seed, duration, flares, args.config)
            for mode in args.modes:
                found = run_mode(sim, base / f"seed{seed}_runs", mode, args.max_far,
                                 template=args.site_config)
                rows = false_detections(sim, found)
                rows["seed"], rows["mode"] = seed, mode
                false.append(rows)
                if args.noise_only:
                    results[mode][seed] = {"false": len(found),
                                           "false_per_hour": len(found) / (duration / 3600)}
                else:
                    rows, unmatched = score(sim, found)
                    results[mode][seed] = summary(rows, unmatched, duration / 3600)
                results[mode][seed]["error_scale"] = found.meta["error_scale"]
                print(mode, seed, json.dumps(results[mode][seed]), flush=True)
    args.json.write_text(json.dumps(results, indent=1))
    command = "python studies/real_wafer.py " + " ".join(argv if argv is not None
                                                           else sys.argv[1:])
    made_at = commit()
    seeds = seed_table(results, args.noise_only, duration / 3600, command, made_at)
    seeds.write(args.json.with_name(args.json.stem + "_seeds.ecsv"), overwrite=True)
    print("\n" + (noise_markdown({args.config.stem: [seeds]}) if args.noise_only
                  else flares_markdown(seeds)))
    if args.noise_only and "paper" in results:
        noise_table(seeds, args.site_config, made_at).write(
            args.json.with_name(args.json.stem + "_noise.ecsv"), overwrite=True)
    false = [rows for rows in false if len(rows)]
    false = vstack(false) if false else None
    if false is not None:
        false.write(args.json.with_name(args.json.stem + "_false.ecsv"), overwrite=True)
        print("\n| mode | seed | " + " | ".join(FALSE_COLUMNS) + " |")
        print("| --- " * (len(FALSE_COLUMNS) + 2) + "|")
        for r in false:
            cells = [f"{r[c]:.2f}" if isinstance(r[c], float) else str(r[c])
                     for c in FALSE_COLUMNS]
            print(f"| {r['mode']} | {r['seed']} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
