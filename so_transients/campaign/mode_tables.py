"""The two search modes on the same grid, each held to the paper's false-alarm rate by ``far``,
as the Markdown of their results page (``docs/results/both_modes.md``): a coherent-mode and a
paper-mode campaign of the same noise and flares (their ``thresholds_far``,
``thresholds_equal_rate`` and ``far_budget`` tables)."""
from __future__ import annotations

import numpy as np

from so_transients.campaign.far_tables import read_far_tables
from so_transients.campaign.markdown import _pm, _rows_by

TABLES = ("far_budget", "thresholds_far", "thresholds_equal_rate")


def read_mode_tables(folder) -> dict:
    """A campaign's results folder's tables that the page shows (:data:`TABLES`)."""
    return read_far_tables(folder, TABLES)


def levels_cell(row) -> str:
    """``S10 ± e / S50 ± e / S90 ± e`` in mJy; ``—`` for a level the grid does not reach."""
    return " / ".join(_pm(row[f"s{level}"], row[f"s{level}_err"]) for level in (10, 50, 90))


def paper_cell(row) -> str:
    """The paper's Table 2 at 10 / 50 / 90 % (empty where it has no row)."""
    values = [float(row[f"paper_s{level}"]) for level in (10, 50, 90)]
    return " / ".join(f"{v:.0f}" for v in values) if all(np.isfinite(values)) else ""


def _number(value: float) -> str:
    return f"{value:.2f}" if np.isfinite(value) else ""


MODES_HEADER = ("| band | t_r (s) | coherent mode, `far` on Z | paper mode, `far` on "
                "`coherent_snr` | paper mode, raised S/N cut | paper's Table 2 | 90 %: coherent "
                "/ paper mode | 90 %: Table 2 / coherent |")


def modes_rows(coherent: dict, paper: dict) -> list:
    """Per band and t_r of the coherent campaign's ``thresholds_far``: its row, the paper-mode
    campaign's rows at the budget and at the raised fitted-S/N cut (``None`` where that
    campaign has no such cell), and the two ratios of 90 % thresholds."""
    at_budget = _rows_by(paper["thresholds_far"])[0]
    raised = _rows_by(paper["thresholds_equal_rate"])[0]
    rows = []
    for c in coherent["thresholds_far"]:
        key = (str(c["band"]), float(c["t_rise"]))
        p = at_budget.get(key)
        rows.append(dict(band=key[0], t_rise=key[1], coherent=c, paper=p, raised=raised.get(key),
                         coherent_over_paper=float(c["s90"]) / float(p["s90"]) if p else np.nan,
                         table2_over_coherent=float(c["paper_s90"]) / float(c["s90"])))
    return rows


def modes_markdown(pairs) -> str:
    """S_p at 10 / 50 / 90 % of both modes, cell by cell (:func:`modes_rows`), for each
    ``(coherent, paper)`` pair of :func:`read_mode_tables` results (one per band's grid)."""
    lines = [MODES_HEADER, "| --- | ---: | --- | --- | --- | --- | ---: | ---: |"]
    for r in (row for coherent, paper in pairs for row in modes_rows(coherent, paper)):
        paper_cells = [levels_cell(r[k]) if r[k] is not None else "" for k in ("paper", "raised")]
        lines.append(f"| {r['band']} | {r['t_rise']:g} | {levels_cell(r['coherent'])} | "
                     f"{paper_cells[0]} | {paper_cells[1]} | {paper_cell(r['coherent'])} | "
                     f"{_number(r['coherent_over_paper'])} | "
                     f"{_number(r['table2_over_coherent'])} |")
    return "\n".join(lines) + "\n"


BUDGET_HEADER = ("| band | mode | statistic | slide-hours | inverted data (h) | Z at the paper's "
                 "rate: passing / failing the chi-squared test | noise-only detections above "
                 "it (expected) |")


def budget_markdown(runs) -> str:
    """A row per campaign and band (``(mode, read_mode_tables(...))`` pairs): the background's
    hours, the Z budget for a candidate passing and failing the test, and the noise-only
    detections reaching it against the number the rate expects."""
    lines = [BUDGET_HEADER, "| --- | --- | --- | ---: | ---: | ---: | ---: |"]
    for mode, tables in runs:
        for b in tables["far_budget"]:
            lines.append(f"| {b['band']} | {mode} | `{b['statistic']}` | {b['slide_hours']:.1f} "
                         f"| {b['data_hours']:.2f} | {b['z_budget']:.2f} / "
                         f"{b['z_budget_chi2_failed']:.2f} | {b['n_noise_above']} "
                         f"({b['expected_above']:.2f}) |")
    return "\n".join(lines) + "\n"
