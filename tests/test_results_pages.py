"""Results pages against the committed tables behind them (docs/results/data): each number a
page quotes from a table is that table's."""
import re
from pathlib import Path

import numpy as np
from astropy.table import Table

from so_transients.campaign.drawn_wafer import config_summaries

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"


def markdown_rows(page: Path, header_start: str, after: str | None = None,
                  header: bool = False) -> list:
    """The body rows (lists of cells) of the Markdown table of ``page`` whose header row
    starts with ``header_start`` (the first after the line ``after``, if given); with
    ``header``, the header's cells first."""
    lines = page.read_text().splitlines()
    first = lines.index(after) if after is not None else 0
    start = next(i for i, line in enumerate(lines) if i > first and line.startswith(header_start))
    rows = [[c.strip() for c in lines[start].strip("|").split("|")]] if header else []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


def test_the_paired_full_check_on_the_table2_page_is_its_table():
    table = Table.read(RESULTS / "data" / "full_check.ecsv")
    rows = markdown_rows(RESULTS / "table2.md", "| band | t_r (s) | S_p (mJy) | flares | fast path "
                                                  "| full pipeline | fast only")
    assert [r[0] for r in rows] == list(table["band"])
    for cells, row in zip(rows, table):
        numbers = [float(c) for c in cells[1:]]
        expect = [row[k] for k in ("t_rise", "s_peak", "n", "fast_detected", "full_detected",
                                   "fast_only", "full_only")]
        assert numbers[:7] == expect, row["band"]
        assert numbers[7] == float(f"{row['mcnemar_p']:.2g}"), row["band"]
    # the page's conclusion: no band differs at 5 %
    assert (np.asarray(table["mcnemar_p"]) > 0.05).all()
    assert re.search(r"every p > 0\.05", (RESULTS / "table2.md").read_text())


def test_the_drawn_wafer_summaries_are_their_tables():
    """The drawn-wafer page's summaries (both simulators, both shipped configs) are the sums of
    the per-realization tables behind them, and they meet issue 45's bounds: at least 20
    realizations, 95 % of the 3 Jy flares found and within 10 % and 0.2', none mislocated."""
    page = RESULTS / "drawn_wafers.md"
    rows = markdown_rows(page, "| simulator | table | config | realizations |")
    assert {(r[0], r[2]) for r in rows} == {(s, c) for s in ("this package's", "TOAST 3")
                                            for c in ("preprocess_paper.yaml",
                                                      "preprocess_production.yaml")}
    for cells in rows:
        table = Table.read(RESULTS / cells[1].strip("`"))
        assert config_summaries(table[table["config"] == cells[2]]) == [cells[2:]], cells[:3]
        n, found, good = int(cells[3]), int(cells[4].split(" / ")[0]), int(cells[5].split()[0])
        crossed = int(cells[4].split(" / ")[1])
        assert n >= 20 and found >= 0.95 * crossed and good >= 0.95 * crossed, cells[:3]
        assert cells[10] == "0", cells[:3]
    noise = markdown_rows(page, "| config | detectors | table | seeds | false detections |")
    assert {(r[0], r[1]) for r in noise} == {("preprocess_paper.yaml", "drawn"),
                                             ("preprocess_paper.yaml", "ideal"),
                                             ("preprocess_production.yaml", "drawn")}
    for config, _, name, seeds, false, hours, rate in noise:
        table = Table.read(RESULTS / name.strip("`"))
        mine = table[table["config"] == config]
        total = float(np.sum(mine["hours"]))
        assert seeds == f"{min(mine['seed'])}-{max(mine['seed'])}"
        assert len(set(mine["seed"])) == max(mine["seed"]) - min(mine["seed"]) + 1
        assert [int(false), float(hours)] == [int(np.sum(mine["false"])), round(total, 2)]
        assert float(rate) == round(int(np.sum(mine["false"])) / total, 2)
        assert total >= 5


def test_the_score_page_is_the_shipped_models_figures():
    """The score page's table of held-out candidates is what the shipped model records of
    itself (``figures`` in so_transients/score/models/real_score.json, written by training)."""
    import json

    model = Path(__file__).resolve().parents[1] / "so_transients" / "score" / "models"
    figures = json.loads((model / "real_score.json").read_text())["figures"]
    rows = markdown_rows(RESULTS / "score.md", "| held out | mode | candidates | real |")
    assert len(rows) == 8
    for held, mode, kind, real, false, at99, at999, real_kept, false_kept in rows:
        fig = figures["scan" if "other scan" in held else "test"][f"{mode}/{kind}"]
        f99, f999, det = fig["0.99"], fig["0.999"], fig["detections"]
        assert [int(real), int(false)] == [f99["n_real"], f99["n_false"]]
        assert at99 == f"{f99['rejected']:.3f} ({f99['cut']:.3f})"
        assert at999 == f"{f999['rejected']:.3f}"
        assert real_kept == f"{det['real_kept']} / {det['real']}"
        assert false_kept == f"{det['artefact_kept']} / {det['artefact']}"

