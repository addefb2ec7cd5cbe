"""The matched filter's compiled loops against the numpy they replace."""
import numpy as np
import pytest

from so_transients.detect import spectral_ops


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_interpolating_above_a_threshold_is_dilating_then_interpolating(seed):
    rng = np.random.default_rng(seed)
    nrows, nsamp, n, threshold = 12, 400, 3, np.float32(3.0)
    snr = 0.5 * rng.standard_normal((nrows, nsamp)).astype(np.float32)
    snr[4:] *= 4            # unit-variance rows beyond: a few random excursions
    # excursions at both ends, runs that touch after dilation and runs that do not
    snr[0, [0, 1, nsamp - 1]] = 5.0
    snr[1, [100, 100 + 2 * n + 1]] = -6.0         # intervals adjacent: one run
    snr[2, [100, 100 + 2 * n + 2]] = 6.0          # one good sample between them
    snr[3] = 4.0                                   # every sample
    x = rng.standard_normal((nrows, nsamp + 50)).astype(np.float32)   # padded rows
    expected = x.copy()
    mask = spectral_ops.dilate_rows(np.abs(snr) > threshold, n)
    spectral_ops.interpolate_runs(expected[:, :nsamp], mask)
    got = x.copy()
    counts = spectral_ops.interpolate_above(got, snr, threshold, n)
    assert np.array_equal(got, expected)
    assert np.array_equal(counts, mask.sum(axis=1))
    assert counts[3] == nsamp and counts[2] == 2 * (2 * n + 1)
