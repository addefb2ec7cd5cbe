"""Labels a person gave on the vetting page (``so-transients report``), as training rows.

The page exports a CSV file: one row per detection of each labelled event, with the event's
UUID, the label (``real``, ``artefact`` or ``unsure``) and the candidate columns the score's
features are computed from (:data:`DETECTION_COLUMNS`). :func:`read_person_labels` reads it
into candidates with 0/1 labels (``unsure`` left out), and :func:`with_person_labels` puts
them beside simulated ones: ``so-transients study train-score --labels FILE``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.table import Table, vstack

from so_transients.score.features import INPUT_COLUMNS

#: The candidate columns :data:`so_transients.score.features.FEATURES` are computed from:
#: what the page carries of each detection, so that its labels can train the score.
DETECTION_COLUMNS = INPUT_COLUMNS

LABEL_VALUES = {"real": 1, "artefact": 0}
KNOWN = set(LABEL_VALUES) | {"unsure"}


def read_person_labels(path) -> Table:
    """The labelled detections of a vetting page's export: :data:`DETECTION_COLUMNS` (float),
    ``event_uuid`` and ``label`` (1 real, 0 artefact; ``unsure`` rows are dropped). Raises
    naming the file and the row when a label or a column is not what the page writes."""
    path = Path(path)
    table = Table.read(path, format="ascii.csv", comment="#", fast_reader=False)
    missing = [c for c in ("event_uuid", "label", *DETECTION_COLUMNS) if c not in table.colnames]
    if missing:
        raise ValueError(f"{path}: not a vetting page's label export: no column(s) {missing}")
    values = np.asarray(table["label"]).astype(str)
    bad = [i for i, v in enumerate(values) if v not in KNOWN]
    if bad:
        raise ValueError(f"{path}: row {bad[0] + 1}: label {values[bad[0]]!r} is not one of "
                         f"{sorted(KNOWN)}")
    keep = values != "unsure"
    out = Table({c: np.asarray(table[c], float)[keep] for c in DETECTION_COLUMNS})
    out["event_uuid"] = np.asarray(table["event_uuid"]).astype(str)[keep]
    out["label"] = np.array([LABEL_VALUES[v] for v in values[keep]], int)
    return out


def with_person_labels(train: Table, paths) -> Table:
    """``train`` (candidates with a ``label`` column) and the labelled detections of each
    file of ``paths`` in one table, on the columns both have."""
    people = [read_person_labels(p) for p in paths]
    if not people:
        return train
    return vstack([train, *people], join_type="inner", metadata_conflicts="silent")
