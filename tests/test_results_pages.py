"""Results pages against the committed tables behind them (docs/results/data): each number a
page quotes from a table is that table's."""
import re
from pathlib import Path

import numpy as np
from astropy.table import Table

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"


def markdown_rows(page: Path, header_start: str) -> list:
    """The body rows (lists of cells) of the Markdown table of ``page`` whose header row
    starts with ``header_start``."""
    lines = page.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header_start))
    rows = []
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
