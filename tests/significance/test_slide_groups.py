"""Grouped time slides: the groups, their offsets, the partial maps and the gate."""
import numpy as np
import pytest

from so_transients.coherent.config import CoherentConfig
from so_transients.coherent.statistic import coherent_map, edge_samples, row_offsets, row_weights
from so_transients.significance.slide_groups import (
    gate_maxima, group_offsets, group_sum, min_group_samples, partial_maps, slide_groups
)
from tests.coherent.test_coherent import ROW_STEP, SIGMA_BEAM, wafer


def test_live_detectors_split_evenly_and_too_few_are_not_grouped():
    rng = np.random.default_rng(1)
    live = np.ones(200, bool)
    live[::7] = False
    groups = slide_groups(live, 16, rng)
    counts = np.bincount(groups[live], minlength=16)
    assert counts.max() - counts.min() <= 1 and counts.sum() == live.sum()
    assert groups.max() == 15
    assert slide_groups(live, 0, rng) is None
    assert slide_groups(np.ones(31, bool), 16, rng) is None     # fewer than 2 per group


def test_a_groups_detectors_move_alike_and_groups_stay_apart():
    rng = np.random.default_rng(2)
    groups = slide_groups(np.ones(300, bool), 16, rng)
    nsamp, min_shift = 6000, 400
    part = (nsamp - 2 * min_shift) // 16
    for _ in range(20):
        offsets = group_offsets(groups, 300, nsamp, min_shift, rng)
        per_group = [np.unique(offsets[groups == g]) for g in range(16)]
        assert all(len(u) == 1 for u in per_group)
        values = np.sort(np.concatenate(per_group))
        assert values.min() >= min_shift and values.max() < nsamp - min_shift
        assert np.diff(values).min() >= part - part // 2
    many = group_offsets(groups, 300, nsamp, min_shift, rng, 50)   # 50 slides at once
    assert many.shape == (50, 300)
    assert all(len(np.unique(many[:, groups == g][k])) == 1 for g in range(16)
               for k in range(50))
    assert len(np.unique(many[:, groups == 0][:, 0])) > 25        # slides differ
    independent = group_offsets(None, 300, nsamp, min_shift, rng)
    assert len(np.unique(independent)) > 250
    assert min_group_samples(16, min_shift, 5) == 2 * min_shift + 320


def test_the_partial_maps_add_up_to_the_map():
    """Summed over the groups, the partial maps are the map (float32), cyclically shifted
    by the lags: a slide whose groups all move by 0 is the data."""
    rng = np.random.default_rng(3)
    geometry, sigma = wafer(rng=rng)
    live = np.ones(len(sigma), bool)
    live[3] = False
    rows = row_offsets(geometry, SIGMA_BEAM, ROW_STEP)
    snr = rng.normal(size=(len(sigma), 3000))
    weights, norm = row_weights(geometry, rows, SIGMA_BEAM, sigma, live)
    groups = slide_groups(live, 8, rng)
    terms = partial_maps(snr, weights, geometry.lag_samples, groups)
    assert terms.shape == (8 * len(rows), 3000)
    total = group_sum(terms, 8) / norm[:, None]
    z, _ = coherent_map(snr, geometry, rows, SIGMA_BEAM, sigma, live, with_flux=False)
    inside = np.ones(z.shape, bool)     # the data's map does not wrap at the scan ends
    inside[:, edge_samples(z.shape[1], geometry.lag_samples)] = False
    assert inside.sum() > 1000
    assert np.allclose(total[inside], z[inside], atol=1e-4)


def test_the_gate_zeroes_the_rows_detectors_where_the_position_passes_them():
    rng = np.random.default_rng(4)
    snr = rng.normal(size=(5, 400))
    weights = np.array([[1.0, 0.5, 0.0, 0.0, 0.2], [0.0, 0.0, 1.0, 1.0, 0.0]])
    lags = np.array([0, 10, -5, 3, 390])
    out = gate_maxima(snr, weights, lags, [0], [100], 4)
    for d, lag in ((0, 0), (1, 10)):
        assert np.all(out[d, 96 + lag:105 + lag] == 0)
        assert np.all(out[d, :96 + lag] == snr[d, :96 + lag])
        assert np.all(out[d, 105 + lag:] == snr[d, 105 + lag:])
    assert np.array_equal(out[2:4], snr[2:4])            # another row's detectors
    # detector 4 passes it past the end (at 490): cyclically, at 90, as the cyclic map sums
    assert np.all(out[4, 86:95] == 0)
    assert np.array_equal(out[4, :86], snr[4, :86]) and np.array_equal(out[4, 95:], snr[4, 95:])
    assert not np.shares_memory(out, snr)
    again = snr.copy()
    assert gate_maxima(again, weights, lags, [0], [100], 4, in_place=True) is again
    assert np.array_equal(again, out)


def test_gating_the_partial_maps_is_summing_the_gated_data():
    rng = np.random.default_rng(7)
    geometry, sigma = wafer(rng=rng)
    live = np.ones(len(sigma), bool)
    rows = row_offsets(geometry, SIGMA_BEAM, ROW_STEP)
    snr = rng.normal(size=(len(sigma), 3000))
    weights, _ = row_weights(geometry, rows, SIGMA_BEAM, sigma, live)
    groups = slide_groups(live, 8, rng)
    lags = geometry.lag_samples
    # one gate inside the scan, one whose crossing wraps past its end, and one overlapping
    # the first (a sample is removed once)
    got = partial_maps(snr, weights, lags, groups)
    gated = gate_maxima(snr, weights, lags, [2, len(rows) // 2, 3], [1500, 2995, 1510], 30,
                        got, groups)
    assert (gated == 0).sum() > 1000
    assert np.array_equal(gated, gate_maxima(snr, weights, lags, [2, len(rows) // 2, 3],
                                             [1500, 2995, 1510], 30))
    expected = partial_maps(gated, weights, lags, groups)
    assert np.allclose(got, expected, atol=1e-4)
    assert not np.allclose(partial_maps(snr, weights, lags, groups), expected, atol=1e-2)


@pytest.mark.parametrize("n_groups", [4, 16])
def test_grouped_slides_keep_the_noise_spread_and_remove_a_source(n_groups):
    """On white noise with a source, a grouped slide's map has the data's noise spread and
    no trace of the gated source where it was."""
    from so_transients.significance.far import SignificanceConfig, scan_maps
    from tests.coherent.test_coherent import inject

    rng = np.random.default_rng(5)
    geometry, sigma = wafer(rng=rng)
    live = np.ones(len(sigma), bool)
    snr = rng.normal(size=(len(sigma), 6000))
    inject(snr, geometry, sigma, 1000.0, 3000, 0.0)
    snr[5, :200] = np.nan                 # cut samples: the step gates its own clean copy
    given = snr.copy()
    cfg = SignificanceConfig(n_slides=20, min_slide_s=1.0, slide_groups=n_groups)
    maps = scan_maps(snr, geometry, SIGMA_BEAM, sigma, live, 0, cfg, CoherentConfig().vetoes,
                     np.random.default_rng(6))
    assert np.array_equal(snr, given, equal_nan=True)               # the caller's untouched
    assert np.nanmax(maps.z) / maps.data_scale > 20                 # the source is there
    # 20 slides' robust spread, each to ~1 %, of white noise: the data's, to 5 %
    assert np.median(maps.slide_scale) == pytest.approx(maps.data_scale, rel=0.05)
    # above the slides' floor only noise: 20 slides of 30 s of white noise on this wafer
    # give a handful of maxima from Z = 4.5 (a Gaussian map's tail), none beyond 6.5
    top = np.asarray(maps.background) / np.median(maps.slide_scale)
    assert len(top) < 40 and (len(top) == 0 or top.max() < 6.5), top
