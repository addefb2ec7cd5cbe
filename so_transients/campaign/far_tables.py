"""The coherent search's false-alarm studies as the Markdown of their results page
(``docs/results/coherent.md``): the ``far`` calibration of ``studies/far_calibration.py``
(its ``levels.ecsv`` and ``calibration.ecsv``) and the time-slide backgrounds of coherent
campaigns (their ``far_budget.ecsv`` and ``thresholds_far.ecsv``)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.table import Table


def pulls(observed, expected) -> np.ndarray:
    """Poisson pulls ``(observed - expected) / sqrt(expected)``."""
    observed, expected = np.asarray(observed, float), np.asarray(expected, float)
    return (observed - expected) / np.sqrt(expected)


LEVELS_HEADER = ("| Z >= | data maxima | sign-inverted maxima | slides, in the data's live "
                 "time | far x live time |")


def levels_markdown(levels: Table) -> str:
    """The data map's local maxima above each Z against the two backgrounds' (the slides'
    count scaled to the data's live time, and ``far``, the step's rate, times it)."""
    lines = [LEVELS_HEADER, "| ---: | ---: | ---: | ---: | ---: |"]
    for r in levels:
        lines.append(f"| {r['z']:.1f} | {r['data_maxima']} | {r['inverted_maxima']} | "
                     f"{r['far_slides_x_live']:.1f} | {r['far_x_live']:.1f} |")
    return "\n".join(lines) + "\n"


CALIBRATION_HEADER = ("| x (per wafer-band-hour) | data maxima with far <= x | x times the live "
                      "time | pull |")


def calibration_markdown(calibration: Table) -> str:
    """For each ``x``, the data maxima whose ``far`` is at most ``x`` against ``x`` times the
    data's live time, with the Poisson pull (``-`` where less than one is expected)."""
    lines = [CALIBRATION_HEADER, "| ---: | ---: | ---: | ---: |"]
    pull = pulls(calibration["maxima_far_below"], calibration["expected"])
    for r, p in zip(calibration, pull):
        shown = f"{p:+.1f}" if r["expected"] >= 1 else "-"
        lines.append(f"| {_number(r['far_per_hour'])} | {r['maxima_far_below']} | "
                     f"{_number(r['expected'])} | {shown} |")
    return "\n".join(lines) + "\n"


def _number(value: float) -> str:
    """Three significant figures below 100, whole numbers above."""
    return f"{value:.3g}" if value < 100 else f"{value:,.0f}"


def read_far_tables(folder, names=("far_budget", "thresholds_far")) -> dict:
    """A coherent campaign's results folder's tables ``names`` (by default its ``far_budget``
    and ``thresholds_far``), by name."""
    folder = Path(folder)
    return {name: Table.read(folder / f"{name}.ecsv") for name in names}


SLIDES_HEADER = ("| band | slides | slide-hours | slides' maxima from Z = 4.5 | budget: passing / "
                 "failing the test | noise-only above it (expected) | 90 % thresholds (mJy), "
                 "t_r 0.5-30 s |")


def slides_markdown(runs) -> str:
    """A row per coherent campaign (``(slides description, read_far_tables(...))`` pairs): its
    band, the slides' hours and maxima, the Z at the paper's rate for a candidate passing and
    failing the chi-squared test, the noise-only detections reaching it against the number
    expected at that rate, and the 90 % thresholds at that budget."""
    lines = [SLIDES_HEADER, "| --- | --- | ---: | ---: | ---: | ---: | --- |"]
    for slides, tables in runs:
        for b in tables["far_budget"]:
            band = str(b["band"])
            t = tables["thresholds_far"][tables["thresholds_far"]["band"] == band]
            s90 = ", ".join(f"{v:.0f}" for v in t["s90"])
            lines.append(f"| {band} | {slides} | {b['slide_hours']:.1f} | {b['n_slide_maxima']:,} "
                         f"| {b['z_budget']:.2f} / {b['z_budget_chi2_failed']:.2f} | "
                         f"{b['n_noise_above']} ({b['expected_above']:.2f}) | {s90} |")
    return "\n".join(lines) + "\n"
