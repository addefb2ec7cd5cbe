"""The compiled DBSCAN gives scikit-learn's labels exactly."""
import numpy as np
import pytest
from sklearn.cluster import DBSCAN

from so_transients.detect.dbscan import dbscan_labels


def _clumps(rng, n_clumps, per, spread, noise, size=1.0):
    centres = rng.uniform(0, size, (n_clumps, 2))
    pts = [c + rng.normal(0, spread, (per, 2)) for c in centres]
    return np.concatenate(pts + [rng.uniform(0, size, (noise, 2))])


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("min_samples", [1, 3, 5, 12])
def test_labels_equal_scikit_learn(seed, min_samples):
    rng = np.random.default_rng(seed)
    # touching clumps and scattered noise: border points shared by clusters, chains, singletons
    points = rng.permutation(_clumps(rng, 6, 40, 0.02, 300))
    eps = 0.03
    expect = DBSCAN(eps=eps, min_samples=min_samples).fit(points).labels_
    got = dbscan_labels(points, eps, min_samples)
    assert np.array_equal(got, expect)
    assert len(np.unique(expect)) > 2          # the case has clusters and noise


def test_exact_distances_and_edge_cases():
    # points on a line 1 apart: eps just above 1 links them all, just below links none
    line = np.c_[np.arange(6.0), np.zeros(6)]
    assert np.array_equal(dbscan_labels(line, 1.0 + 1e-9, 3), np.zeros(6))
    assert np.array_equal(dbscan_labels(line, 1.0 - 1e-9, 2), np.full(6, -1))
    # ends of the chain are border points (two neighbours counting themselves)
    assert np.array_equal(dbscan_labels(line, 1.0 + 1e-9, 3),
                          DBSCAN(eps=1.0 + 1e-9, min_samples=3).fit(line).labels_)
    assert dbscan_labels(np.zeros((0, 2)), 0.1).shape == (0,)
    assert np.array_equal(dbscan_labels(np.zeros((1, 2)), 0.1, 1), [0])
    with pytest.raises(ValueError, match="eps"):
        dbscan_labels(line, 0.0)
