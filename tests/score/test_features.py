"""The score's features and the candidate columns they read."""
import numpy as np

from so_transients.common import candidates
from so_transients.score.features import FEATURES, INPUT_COLUMNS, feature_matrix, input_columns


def test_the_input_columns_are_what_the_features_read():
    """A table holding only INPUT_COLUMNS gives every feature as the whole candidate table
    does, and each of those columns is in the candidate schema (the vetting pages export
    exactly these, so that a person's labels can train the score)."""
    assert set(INPUT_COLUMNS) <= {c.name for c in candidates.columns(saved=True)}
    rng = np.random.default_rng(1)
    full = {c.name: rng.uniform(1, 2, 5) for c in candidates.columns(saved=True)
            if c.kind in ("int", "float")}
    only = {name: full[name] for name in INPUT_COLUMNS}
    assert np.array_equal(feature_matrix(only), feature_matrix(full))
    assert input_columns(["peak_ratio"]) == ("snr_max", "snr_fit")
    for name in FEATURES:    # dropping any input (but snr_max, which every table has) changes it
        for col in set(input_columns([name])) - {"snr_max"}:
            fewer = {k: v for k, v in only.items() if k != col}
            assert not np.array_equal(feature_matrix(fewer, [name]), feature_matrix(only, [name]))
