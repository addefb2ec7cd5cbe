"""The both-modes page's tables (so_transients.campaign.mode_tables) on a committed coherent
grid: every cell is its campaign's row, and the ratios are those of the 90 % thresholds."""
from pathlib import Path

import numpy as np

from so_transients.campaign.mode_tables import (
    budget_markdown, levels_cell, modes_markdown, modes_rows, read_mode_tables
)

DATA = Path(__file__).resolve().parents[2] / "docs" / "results" / "data" / "coherent"


def test_each_row_is_its_cell_and_its_ratios_are_the_90_percent_thresholds():
    coherent = read_mode_tables(DATA / "campaign_coherent_far")
    # a stand-in for the paper-mode campaign: the same grid at the raised fitted-S/N cut,
    # one cell short, so that a missing cell shows as empty
    paper = {"thresholds_far": coherent["thresholds_equal_rate"][1:],
             "thresholds_equal_rate": coherent["thresholds_equal_rate"]}
    rows = modes_rows(coherent, paper)
    assert len(rows) == len(coherent["thresholds_far"])
    assert rows[0]["paper"] is None and np.isnan(rows[0]["coherent_over_paper"])
    for r in rows[1:]:
        assert r["coherent_over_paper"] == r["coherent"]["s90"] / r["paper"]["s90"]
        assert r["coherent_over_paper"] < 1        # the raised cut's thresholds are higher
    lines = modes_markdown([(coherent, paper)]).splitlines()
    assert len(lines) == 2 + len(rows)
    for line, r in zip(lines[2:], rows):
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[:3] == [r["band"], f"{r['t_rise']:g}", levels_cell(r["coherent"])]
        table2 = r["coherent"]["paper_s90"]
        assert cells[7] == (f"{table2 / r['coherent']['s90']:.2f}" if np.isfinite(table2) else "")
    assert lines[2].split("|")[4].strip() == ""   # the missing cell


def test_a_level_the_grid_does_not_reach_is_a_dash_and_the_budget_has_a_row_per_band():
    coherent = read_mode_tables(DATA / "campaign_coherent_far")
    row = dict(coherent["thresholds_far"][0])
    row["s10"] = np.nan
    assert levels_cell(row).startswith("— / ")
    f150 = read_mode_tables(DATA / "campaign_coherent_far_f150")
    lines = budget_markdown([("coherent", coherent), ("coherent", f150)]).splitlines()
    assert [line.split("|")[1].strip() for line in lines[2:]] == ["f090", "f150"]
    b = f150["far_budget"][0]
    assert f"| {b['z_budget']:.2f} / {b['z_budget_chi2_failed']:.2f} |" in lines[3]
