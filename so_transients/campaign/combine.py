"""Several campaigns' results as one: the paper's four bands from an MF and a UHF campaign.

Each campaign writes its input tables (:data:`.report.INPUT_TABLES`) to its results folder;
this stacks them (a band must come from one campaign only) and derives and writes every table,
``summary.md`` and the figures again, over all bands (``so-transients study combine``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.table import Table, vstack

from so_transients.campaign.provenance import repository_path
from so_transients.campaign.report import INPUT_TABLES, OPTIONAL_TABLES, write_tables


def read_results(folder) -> dict:
    """The input tables of one campaign's results folder (:data:`.report.OPTIONAL_TABLES`
    may be absent)."""
    folder = Path(folder)
    tables = {}
    for name in INPUT_TABLES:
        path = folder / f"{name}.ecsv"
        if not path.exists():
            if name in OPTIONAL_TABLES:
                tables[name] = None
                continue
            raise ValueError(f"{path} is missing: is {folder} a campaign's results folder of "
                             f"this version (rerun the campaign to write it)?")
        tables[name] = Table.read(path)
    return tables


def combine_results(folders, out) -> Path:
    """Stack the results of ``folders`` and write everything to ``out``."""
    parts = [read_results(f) for f in folders]
    seen = {}
    for folder, part in zip(folders, parts):
        for band in set(np.asarray(part["efficiency"]["band"]).astype(str)):
            if band in seen:
                raise ValueError(f"band {band} is in both {seen[band]} and {folder}")
            seen[band] = folder
    # what each part's tables say of their run (command, commit, site config), kept
    comments = [f"{repository_path(f, 2)}: "
                + "; ".join(part["efficiency"].meta.get("comments", []))
                for f, part in zip(folders, parts)]
    tables = {}
    for name in INPUT_TABLES:
        found = [p[name] for p in parts if p[name] is not None and len(p[name])]
        for table in found:
            table.meta.clear()
        tables[name] = vstack(found) if found else (None if name in OPTIONAL_TABLES else
                                                   parts[0][name])
    meta = {"combined_from": [repository_path(f, 2) for f in folders], "comments": comments}
    return write_tables(out, tables, meta)
