"""A campaign's 90 % thresholds and noise-only detections at cuts on the real-or-artefact score.

    so-transients study campaign studies/configs/campaign_paper_far_scored.yaml
    python studies/score_thresholds.py data/campaign_paper_far_scored --cuts 0.3 0.6 0.9

The campaign runs ``transient_fit`` with a ``score_model`` and no ``min_real_score``, so its
detections (``units/*.detections.ecsv``) and its noise-only candidates
(``noise/groups/*/fitted_noise.ecsv``) carry ``real_score``. For each cut, a flare is detected
as the campaign's false-alarm budget counts it (its statistic within the budget,
:func:`so_transients.campaign.far_budget.budget_margin`) and its detection scores at least the
cut; the budget itself (from the time slides and the sign-inverted data) does not move. Prints
the thresholds per t_r and the noise-only detections within the budget, per cut; then the same
at the paper's fitted S/N >= 5 without the budget, with the noise-only and sign-inverted
detections. The thresholds within the budget are written to the campaign's results folder,
``thresholds_far_score.ecsv`` (no cut) and ``thresholds_far_score<cut>.ecsv``, for
``studies/sensitivity_timescale.py``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from astropy.table import Table, vstack

from so_transients.campaign.equal_rate import efficiency_at
from so_transients.campaign.far_budget import (
    budget_margin, budget_table, live_statistics, pooled_backgrounds
)
from so_transients.campaign.report import flux_residual_table, threshold_table


def _read_all(paths) -> Table:
    parts = [t for t in (Table.read(p) for p in sorted(paths)) if len(t)]
    return vstack(parts, metadata_conflicts="silent") if parts else Table()


def noise_candidates(folder: Path, kind="noise") -> Table:
    """Every candidate fitted on the campaign's noise-only data (``kind`` ``inverted``: on
    its sign-inverted copy), with its band and score."""
    parts = []
    for path in sorted((folder / "noise" / "groups").glob(f"*/fitted_{kind}.ecsv")):
        t = Table.read(path)
        if len(t):
            t["band"] = t["bandpass"]
            parts.append(t)
    return vstack(parts, metadata_conflicts="silent")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("campaign", type=Path, help="the campaign's output folder")
    p.add_argument("--cuts", type=float, nargs="+", default=[0.3, 0.6, 0.9])
    args = p.parse_args(argv)
    folder, results = args.campaign, args.campaign / "results"
    seed = json.loads((folder / "campaign.json").read_text())["config"]["seed"]
    flares = Table.read(results / "flares.ecsv")
    dets = _read_all((folder / "units").glob("*.detections.ecsv"))
    if "real_score" not in dets.colnames or np.isnan(np.asarray(dets["real_score"])).all():
        p.error(f"{folder}: its detections carry no real_score (run it with a score_model)")
    matched = flux_residual_table(dets)
    score = np.asarray(dets["real_score"], float)
    live, maxima = Table.read(results / "far_live.ecsv"), Table.read(results / "far_background.ecsv")
    statistics = live_statistics(live)
    backgrounds = pooled_backgrounds(maxima, live)
    false = Table.read(results / "false_positives.ecsv")
    hours = {str(r["band"]): float(r["wafer_hours"]) for r in false}
    noise, inverted = noise_candidates(folder), noise_candidates(folder, "inverted")
    budget = budget_table(backgrounds, noise, hours, statistics)
    budgets = {str(r["band"]): (float(r["z_budget"]), float(r["z_stack_budget"]),
                                float(r["z_budget_chi2_failed"])) for r in budget}
    margin = budget_margin(matched, "bandpass", statistics, budgets)
    noise_margin = budget_margin(noise, "band", statistics, budgets)
    noise_in = np.asarray(noise["detected"], bool) & (np.nan_to_num(noise_margin, nan=-1) >= 0)
    noise_score = np.asarray(noise["real_score"], float)
    rows = []
    for cut in [None] + list(args.cuts):
        keep = np.ones(len(score), bool) if cut is None else score >= cut
        matched["budget_margin"] = np.where(keep, margin, -np.inf)
        eff = efficiency_at(flares, matched, {band: 0.0 for band in backgrounds},
                            column="budget_margin")
        thresholds = threshold_table(eff, seed)
        n_noise = int((noise_in & (True if cut is None else noise_score >= cut)).sum())
        matched["fit_cut"] = np.where(keep, np.asarray(matched["snr_fit"], float), -np.inf)
        at_snr = threshold_table(efficiency_at(flares, matched, {b: 5.0 for b in hours},
                                               column="fit_cut"), seed)
        n_fit = sum(int((np.asarray(t["detected"], bool)
                         & (True if cut is None else np.asarray(t["real_score"]) >= cut)).sum())
                    for t in (noise, inverted))
        rows.append((cut, thresholds, n_noise, at_snr, n_fit))
        thresholds.meta["real_score_cut"] = cut
        thresholds.write(results / f"thresholds_far_score{'' if cut is None else f'{cut:g}'}.ecsv",
                         overwrite=True)
    print_table(rows, 1, 2, f"noise-only within the budget ({sum(hours.values()):.0f} wbh)")
    print("\nAt the paper's fitted S/N >= 5 (no budget):\n")
    print_table(rows, 3, 4, f"noise-only and inverted detections "
                            f"({2 * sum(hours.values()):.0f} wbh)")


def print_table(rows, thresholds_at, count_at, count_name):
    """A Markdown row per cut: the 90 % thresholds (``row[thresholds_at]``) per t_r and the
    count ``row[count_at]``."""
    t_rises = list(rows[0][thresholds_at]["t_rise"])
    print("| cut | " + " | ".join(f"t_r {t:g} s" for t in t_rises) + f" | {count_name} |")
    print("| --- " * (len(t_rises) + 2) + "|")
    for row in rows:
        cut, thresholds = row[0], row[thresholds_at]
        cells = [f"{a:.0f} ± {b:.0f}" for a, b in zip(thresholds["s90"], thresholds["s90_err"])]
        label = "no cut" if cut is None else f"real_score >= {cut:g}"
        print(f"| {label} | " + " | ".join(cells) + f" | {row[count_at]} |")

if __name__ == "__main__":
    main()
