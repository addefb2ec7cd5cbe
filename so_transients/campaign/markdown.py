"""``summary.md``: a campaign's results as Markdown tables, next to the paper's.

Thresholds (ours and at the paper's false-detection rate), flux residuals, pointing, false
detections per wafer-band-hour and the full-pipeline check, each table in the units the README
uses (mJy, arcsec, per wafer-band-hour).
"""
from __future__ import annotations

import numpy as np

from so_transients.campaign.equal_rate import PAPER_RATE_PER_WBH


def _f(value, fmt="{:.0f}"):
    return fmt.format(value) if np.isfinite(value) else "—"


def _pm(value, err, fmt="{:.0f}"):
    if not np.isfinite(value):
        return "—"
    return f"{fmt.format(value)} ± {fmt.format(err)}" if np.isfinite(err) else fmt.format(value)


#: A threshold more than this far from the paper's (as a share of it) is marked in bold.
PAPER_DIFFERENCE = 0.30


def _band_table(bands, t_rises, cell):
    """Rows of t_r, a column per band; ``cell(band, t_rise)`` gives each cell's text."""
    lines = ["| t_r (s) | " + " | ".join(bands) + " |", "|---:|" + "---:|" * len(bands)]
    for t_rise in t_rises:
        lines.append(f"| {t_rise:g} | " + " | ".join(cell(b, t_rise) for b in bands) + " |")
    return lines + [""]


def _rows_by(table):
    """``{(band, t_rise): row}`` and the sorted bands and rise times of ``table``."""
    rows = {(str(r["band"]), float(r["t_rise"])): r for r in table}
    return rows, sorted({b for b, _ in rows}), sorted({t for _, t in rows})


def threshold_cell(row, level) -> str:
    """``ours ± error (paper)``, the paper's value in bold when ours differs from it by more
    than :data:`PAPER_DIFFERENCE`; ``—`` for a level not reached on the grid."""
    if row is None:
        return ""
    ours, paper = _pm(row[f"s{level}"], row[f"s{level}_err"]), row[f"paper_s{level}"]
    if not np.isfinite(paper):
        return ours
    far = np.isfinite(row[f"s{level}"]) and abs(row[f"s{level}"] / paper - 1) > PAPER_DIFFERENCE
    return f"{ours} ({'**' if far else ''}{paper:.0f}{'**' if far else ''})"


def thresholds_section(limits, title):
    """One table per efficiency level: t_r rows, a column per band."""
    rows, bands, t_rises = _rows_by(limits)
    lines = [f"## {title}", "",
             "S_p (mJy) at 10 / 50 / 90 % efficiency, ± bootstrap; the paper's (Clancy et al. "
             f"2025, Table 2) in brackets, **bold** where ours differs from it by more than "
             f"{100 * PAPER_DIFFERENCE:.0f} %.", ""]
    for level in (10, 50, 90):
        lines += [f"{level} % efficiency:", ""]
        lines += _band_table(bands, t_rises,
                             lambda b, t: threshold_cell(rows.get((b, t)), level))
    return lines


def flux_cell(row) -> str:
    """``median ± scatter % (nearest peak %)``."""
    if row is None:
        return ""
    return (f"{_f(100 * row['median'], '{:+.0f}')} ± {_f(100 * row['scatter'])} % "
            f"({_f(100 * row['peak_median'], '{:+.0f}')} %)")


def flux_section(summary):
    rows, bands, t_rises = _rows_by(summary)
    lines = ["## Flux residuals", "",
             "Median (fitted - injected at the detection's time) / injected ± half the 16-84 % "
             "range over every matched detection; in brackets the median (fitted - S_p) / S_p "
             "of the detection nearest each flare's peak. The paper: within 20 % for t_r >= "
             "5 s, low for the fastest flares.", ""]
    return lines + _band_table(bands, t_rises, lambda b, t: flux_cell(rows.get((b, t))))


def pointing_section(pointing):
    lines = ["## Pointing", "", "Fitted position against the truth over every matched detection:", "",
             "| band | detections | median offset | 68 % radius | median / FWHM | 68 % / FWHM "
             "| paper median |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in pointing:
        lines.append(f"| {r['band']} | {r['n']:,} | {r['median']:.1f}″ | {r['p68']:.1f}″ | "
                     f"{100 * r['median_over_fwhm']:.1f} % | {100 * r['p68_over_fwhm']:.1f} % | "
                     f"{_f(r['paper_median'], '{:.1f}')}″ |")
    return lines + [""]


def false_section(false, equal):
    lines = ["## False detections per wafer-band-hour", "",
             "Noise-only data and their sign-inverted copy, Poisson errors (1 when none); the "
             "paper's ~2 per hour over 24 MF wafer-bands and ~1 per hour over 12 UHF "
             "wafer-bands are 0.08 per wafer-band-hour. Last columns: the fitted-S/N "
             "threshold at which the modelled noise-only rate is the paper's "
             "(`equal_rate.ecsv`; never below the cut of 5), and the measured count above 5 "
             "against the tail model's.",
             "",
             "| band | wafer-band-hours | noise-only | inverted | paper | S/N at paper's rate "
             "| above 5: measured / model |", "|---|---:|---:|---:|---:|---:|---:|"]
    eq = {str(r["band"]): r for r in equal}
    for r in false:
        band = str(r["band"])
        e = eq.get(band)
        at = _pm(e["snr_threshold"], e["snr_threshold_err"], "{:.2f}") if e else "—"
        if e and e["basis"] != "tail model":
            at += f" ({e['basis']}: the cut)"
        check = f"{e['n_above_cut']} / {_f(e['model_above_cut'], '{:.1f}')}" if e else "—"
        lines.append(f"| {band} | {r['wafer_hours']:.2f} | {r['n_noise']}: "
                     f"{r['rate_noise_per_wbh']:.2f} ± {r['rate_noise_per_wbh_err']:.2f} | "
                     f"{r['n_inverted']}: {r['rate_inverted_per_wbh']:.2f} ± "
                     f"{r['rate_inverted_per_wbh_err']:.2f} | "
                     f"{PAPER_RATE_PER_WBH.get(band, np.nan):.2f} | {at} | {check} |")
    return lines + [""]


def far_section(budget):
    """Detection at a false-alarm budget (:mod:`.far_budget`)."""
    if budget is None or not len(budget):
        return []
    statistic = str(budget["statistic"][0])
    lines = ["## The false-alarm budget on the coherent Z", "",
             "Background of the noise-only hours (`transient_significance`: time slides and "
             "the sign-inverted data, `far_background.ecsv`); `z_budget`: the lowest Z whose "
             f"`far` is the paper's rate. Noise-only detections with `{statistic}` at least "
             "that high, against the number the budget expects. With sweep stacking, single "
             "crossings and stacks (their own budget, from the inverted data's stacks) get "
             "half the rate each. A detection that fails the chi-squared test is held to the "
             "Z of every background maximum, tested or not. Thresholds in the next section.",
             "", "| band | paper's rate | Z at that rate | stacks' Z | Z failing the "
             "chi-squared test | slides (h) | inverted data (h) | noise-only above: "
             "measured / expected |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in budget:
        z_stack, z_failed = (r[k] if k in budget.colnames else np.nan
                             for k in ("z_stack_budget", "z_budget_chi2_failed"))
        lines.append(f"| {r['band']} | {r['target_per_wbh']:.3f} | {_f(r['z_budget'], '{:.2f}')}"
                     f" | {_f(z_stack, '{:.2f}')} | {_f(z_failed, '{:.2f}')} | "
                     f"{r['slide_hours']:.1f} | "
                     f"{r['data_hours']:.2f} | {r['n_noise_above']} / "
                     f"{r['expected_above']:.2f} |")
    return lines + [""]


def check_section(check):
    if check is None or not len(check):
        return []
    names = check.colnames
    lines = ["## Full site pipeline against the fast path", "",
             "| " + " | ".join(names) + " |", "|" + "---|" * len(names)]
    for r in check:
        lines.append("| " + " | ".join(_cell(r[n]) for n in names) + " |")
    return lines + [""]


def _cell(value):
    if isinstance(value, (float, np.floating)):
        return f"{value:.3g}"
    return str(value)


def summary_markdown(tables: dict) -> str:
    """The whole summary from :func:`.report.write_tables`' tables."""
    lines = ["# Injection-recovery campaign", ""]
    lines += thresholds_section(tables["thresholds"], "Thresholds (detected by the search steps "
                                "as configured: by default fitted S/N >= 5)")
    lines += thresholds_section(tables["thresholds_equal_rate"],
                                "Thresholds at the paper's false-detection rate")
    lines += flux_section(tables["flux_summary"])
    lines += pointing_section(tables["pointing"])
    lines += false_section(tables["false_positives"], tables["equal_rate"])
    if tables.get("thresholds_far") is not None:
        lines += far_section(tables["far_budget"])
        lines += thresholds_section(tables["thresholds_far"],
                                    "Thresholds at the paper's rate by the coherent Z's far")
    lines += check_section(tables.get("full_check"))
    return "\n".join(lines)
