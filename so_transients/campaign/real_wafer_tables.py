"""The real-wafer study's results as tables (one row per search mode and seed, naming the
command and commit that ran) and as the Markdown of its results page
(``docs/results/real_wafer.md``; ``studies/real_wafer.py`` writes the tables)."""
from __future__ import annotations

import numpy as np
from astropy.table import Table

from so_transients.campaign.provenance import commit, stamp


def seed_table(results, noise_only, hours, command, made_at=None) -> Table:
    """Every mode's results (``{mode: {seed: summary}}``) as one row per mode and seed: with
    flares, the 3 Jy and 900 mJy flares crossed, found and found more than once, the 3 Jy flux
    ratios (median, worst), the largest 3 Jy offset (arcmin) and the unmatched detections;
    noise only, the false detections; both with the wafer-band-hours and the largest error
    scale the fit used. ``made_at``: the commit that ran (this checkout's by default)."""
    made_at = made_at or commit()
    rows = []
    for mode, per_seed in results.items():
        for seed, r in per_seed.items():
            row = dict(mode=mode, seed=int(seed), hours=hours,
                       error_scale_max=max(r["error_scale"], default=np.nan))
            if noise_only:
                row["false"] = int(r["false"])
            else:
                for name in ("bright", "faint"):
                    row.update({f"{name}_{k}": int(r[name][k])
                                for k in ("crossed", "found", "twice")})
                row.update(flux_ratio_median=r["bright_flux_ratio_median"],
                           flux_ratio_worst=r["bright_flux_ratio_worst"],
                           offset_max_arcmin=r["bright_offset_max_arcmin"],
                           unmatched=int(r["unmatched"]))
            rows.append(row)
    table = Table(rows=rows)
    table.meta["comments"] = [command, f"{stamp(made_at)}; {hours * 60:g} minutes "
                              "of one f090 wafer-band per seed"]
    return table


FLARES_HEADER = ("| mode | seed | 3 Jy found | found twice | 900 mJy found | found twice | "
                 "3 Jy flux ratio, median | worst | largest 3 Jy offset | unmatched |")


def flares_markdown(table: Table) -> str:
    """A row per mode and seed of a flare run's :func:`seed_table`."""
    lines = [FLARES_HEADER, "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in table:
        lines.append(f"| {r['mode']} | {r['seed']} | {r['bright_found']} / {r['bright_crossed']}"
                     f" | {r['bright_twice']} | {r['faint_found']} / {r['faint_crossed']} | "
                     f"{r['faint_twice']} | {r['flux_ratio_median']:.3f} | "
                     f"{r['flux_ratio_worst']:.3f} | {r['offset_max_arcmin']:.2f}′ | "
                     f"{r['unmatched']} |")
    return "\n".join(lines) + "\n"


NOISE_HEADER = ("| detectors | mode | seeds | wafer-band-hours | false detections | "
                "per wafer-band-hour | fit's error scale, largest |")


def noise_markdown(runs: dict) -> str:
    """A row per set of detectors and mode of noise-only runs (``{name: [seed tables]}``):
    the seeds, their hours, the false detections and their rate (with its Poisson error, or
    its 90 % upper limit when there is none) and the largest error scale the fit used."""
    lines = [NOISE_HEADER, "| --- | --- | --- | ---: | ---: | ---: | ---: |"]
    for name, tables in runs.items():
        rows = [r for t in tables for r in t]
        for mode in dict.fromkeys(str(r["mode"]) for r in rows):
            mine = [r for r in rows if r["mode"] == mode]
            seeds = sorted(int(r["seed"]) for r in mine)
            hours = sum(float(r["hours"]) for r in mine)
            false = sum(int(r["false"]) for r in mine)
            span = f"{seeds[0]}-{seeds[-1]}" if seeds == list(range(seeds[0], seeds[-1] + 1)) \
                else ", ".join(map(str, seeds))
            lines.append(f"| {name} | {mode} | {span} | {hours:.2f} | {false} | "
                         f"{rate_text(false, hours)} | "
                         f"{max(float(r['error_scale_max']) for r in mine):.2f} |")
    return "\n".join(lines) + "\n"


def rate_text(events: int, hours: float) -> str:
    """A rate per wafer-band-hour: ``events / hours`` with its Poisson error, or, with no
    event, its 90 % upper limit (``ln 10 / hours``)."""
    if events == 0:
        return f"< {np.log(10) / hours:.2f} (90 %)"
    return f"{events / hours:.1f} ± {np.sqrt(events) / hours:.1f}"
