"""The coarse-to-fine search of a time slide's maxima finds those of the full map."""
import numpy as np
import pytest
from scipy import ndimage

from so_transients.coherent.statistic import (
    coherent_map, largest_share, local_maxima, measured_scale, row_offsets, time_slide_offsets
)
from so_transients.significance.far import Background
from so_transients.significance.slide_groups import group_offsets, slide_groups
from so_transients.significance.slide_maxima import QUANTUM, SlideSearch, sample_phases
from tests.coherent.test_coherent import SIGMA_BEAM, ROW_STEP, inject, wafer

NSAMP = 6000


def filtered_noise(n_det, rng, width):
    """Unit-variance noise smoothed over ``width`` samples, as the matched filter's output is
    over a beam crossing time (white noise would give the map peaks one sample wide)."""
    snr = ndimage.gaussian_filter1d(rng.normal(size=(n_det, NSAMP)), width, axis=1)
    return snr / snr.std()


def full_maxima(snr, geometry, rows, sigma, live, offsets, threshold, window):
    z, _ = coherent_map(snr, geometry, rows, SIGMA_BEAM, sigma, live, offsets,
                        with_flux=False, finite=True, dtype=np.float32)
    r, s = local_maxima(z, threshold, window)
    return dict(zip(zip(r.tolist(), s.tolist()), z[r, s])), z


@pytest.mark.parametrize("floor", [3.5, 4.5, 2.0])
@pytest.mark.parametrize("n_groups", [0, 16])
def test_the_search_finds_every_maximum_of_the_full_map(floor, n_groups):
    """On filtered noise with a bright source (scattered by the slides), a dead detector
    and slides past either end: the same maxima, at the same Z (float32 sums), as the full
    map's local maxima from the same threshold, with every detector slid on its own and
    in 16 groups (the search then sums the groups' partial maps). Floor 2 is so near the
    noise that the whole map is summed instead."""
    rng = np.random.default_rng(11)
    geometry, sigma = wafer(rng=rng)
    live = np.ones(len(sigma), bool)
    live[7] = False
    window = geometry.crossing_samples(SIGMA_BEAM)
    snr = filtered_noise(len(sigma), rng, window)
    rows = row_offsets(geometry, SIGMA_BEAM, ROW_STEP)
    inject(snr, geometry, sigma, 3000.0, 3000, rows[len(rows) // 2])
    groups = slide_groups(live, n_groups, rng)
    assert (groups is None) == (n_groups == 0)
    search = SlideSearch(snr, geometry, rows, SIGMA_BEAM, sigma, live, window, groups)
    found, spreads = 0, []
    for _ in range(8):
        offsets = group_offsets(groups, len(sigma), NSAMP, 400, rng)
        r, s, z, scale = search.maxima(offsets, floor)
        expected, full = full_maxima(snr, geometry, rows, sigma, live, offsets,
                                     floor * scale, window)
        assert set(zip(r.tolist(), s.tolist())) == set(expected)
        assert np.allclose(z, [expected[k] for k in zip(r.tolist(), s.tolist())], rtol=1e-5,
                           atol=1e-4 * scale)
        spreads.append(measured_scale(full))
        found += len(r)
    # the threshold's spread, measured once on the first slide's coarse map, is the slides'
    # (their mean: 8 maps' robust spreads of ~2 x 10^4 correlated values, each to ~1.5 %)
    assert scale == pytest.approx(np.mean(spreads), rel=0.02)
    assert found > (0 if floor > 4 else 40)      # the comparison is not empty


def noise_search(seed, live_of=None):
    """A :class:`SlideSearch` of filtered noise on the test wafer, and what it was made
    from: ``(rng, snr, geometry, rows, sigma, live, search)``; ``live_of(geometry, rows)``:
    the live detectors (default all)."""
    rng = np.random.default_rng(seed)
    geometry, sigma = wafer(rng=rng)
    rows = row_offsets(geometry, SIGMA_BEAM, ROW_STEP)
    live = np.ones(len(sigma), bool) if live_of is None else live_of(geometry, rows)
    window = geometry.crossing_samples(SIGMA_BEAM)
    snr = filtered_noise(len(sigma), rng, window)
    search = SlideSearch(snr, geometry, rows, SIGMA_BEAM, sigma, live, window)
    return rng, snr, geometry, rows, sigma, live, search


def screen_and_map(rng, snr, geometry, rows, sigma, live, search):
    """A slide's screen and its full map at the screen's positions."""
    offsets = time_slide_offsets(len(sigma), NSAMP, 400, rng)
    screen = search.coarse_map((geometry.lag_samples + offsets) % NSAMP)
    _, full = full_maxima(snr, geometry, rows, sigma, live, offsets, np.inf, search.window)
    return screen, full[::2, ::search.step]


def test_a_slides_largest_share_is_the_maps():
    rng, snr, geometry, rows, sigma, live, search = noise_search(12)
    offsets = time_slide_offsets(len(sigma), NSAMP, 400, rng)
    r, s, _, _ = search.maxima(offsets, 3.0)
    assert len(r)
    assert np.array_equal(search.largest_share(r, s, offsets),
                          largest_share(snr, geometry, rows, SIGMA_BEAM, sigma, live, r, s,
                                        offsets))


def test_far_below_the_slides_floor_rests_on_the_inverted_data():
    """Slides' maxima are searched from ``slide_floor``: below it they are not counted, so
    ``far_slides`` is NaN and ``far`` is the sign-inverted data's rate."""
    b = Background(np.array([4.6, 5.0, 6.0]), 10.0, np.array([3.2, 3.6, 4.1, 4.8]), 1.0,
                   tail_from=None, floor=3.0, slide_floor=4.5)
    far = b.far([4.0, 4.9])
    assert np.isnan(far["far_slides"][0]) and far["far"][0] == far["far_inverted"][0] == 2.0
    assert far["far_slides"][1] == pytest.approx(0.2) == far["far"][1]
    assert Background(np.zeros(0), 1.0, np.zeros(0), 1.0).slide_floor == 3.0


def test_the_screen_is_the_maps_own_values_to_a_tenth_of_z():
    """The screen (16-bit samples, detectors within 2 beam sigmas) at its positions is the
    full map's to the 0.06 in Z the module's doc states: the left-out detectors carry 0.4 %
    of a row's weight^2, so sqrt(0.004) = 0.063 of the spread, checked at 0.08 (the
    spread of ~10^4 differences is known to a few %); the same spread to 1 %."""
    screen, at = screen_and_map(*noise_search(13))
    assert np.std(screen - at) < 0.08 * measured_scale(at)
    assert measured_scale(screen) == pytest.approx(measured_scale(at), rel=0.01)


def test_a_grouped_screen_is_the_maps_own_values_to_a_thousandth_of_its_spread():
    """With slide groups the screen sums every partial map, each rounded to 1/256 of its
    spread: per position sqrt(G / 12) / 256 of a group's spread, about 0.001 of the map's
    (checked at 0.003), and a glitch far beyond the 16-bit range is clipped, not wrapped
    around."""
    rng = np.random.default_rng(14)
    geometry, sigma = wafer(rng=rng)
    rows = row_offsets(geometry, SIGMA_BEAM, ROW_STEP)
    live = np.ones(len(sigma), bool)
    window = geometry.crossing_samples(SIGMA_BEAM)
    snr = filtered_noise(len(sigma), rng, window)
    snr[100, 2000:2010] = 1e5                     # a glitch: S/N 10^5 on one detector
    groups = slide_groups(live, 8, rng)
    search = SlideSearch(snr, geometry, rows, SIGMA_BEAM, sigma, live, window, groups)
    offsets = group_offsets(groups, len(sigma), NSAMP, 400, rng)
    screen = search.coarse_map(search.term_shifts(offsets))
    _, full = full_maxima(snr, geometry, rows, sigma, live, offsets, np.inf, window)
    at = full[::2, ::search.step]
    scale = measured_scale(at)
    quiet = np.abs(at) < 20 * scale               # away from the glitch
    assert quiet.mean() > 0.99
    assert np.std((screen - at)[quiet]) < 0.003 * scale
    # clipped at 128 spreads of a group's map, 128 / sqrt(8) = 45 of the map's: far above
    # any threshold, so the position is refined and gets the map's own value
    assert np.nanmax(at) > 1000 * scale and np.nanmax(screen) > 30 * scale


def test_sample_phases_rounds_to_the_quantum_and_clips_beyond_it():
    snr = np.array([[0.3, -1.7, 2.0**-9 * 3, 500.0, -500.0, 1.0, 7.0]], np.float32)
    phases = sample_phases(snr, 3, np.full(1, QUANTUM), np.arange(1))
    assert phases.dtype == np.int16 and phases.shape == (3, 1, 3)
    values = phases.transpose(1, 2, 0).reshape(1, -1)[:, :7] * QUANTUM
    assert np.allclose(values[0, [0, 1, 2, 5, 6]], snr[0, [0, 1, 2, 5, 6]], atol=QUANTUM / 2)
    assert values[0, 3] == pytest.approx(128.0, abs=0.01)       # clipped
    assert values[0, 4] == pytest.approx(-128.0, abs=0.01)
    assert phases[1, 0, 2] == 0 and phases[2, 0, 2] == 0        # past the end


def test_a_row_the_screens_reach_leaves_empty_sums_as_far_as_the_maps():
    """Detectors dead within 2 beam sigmas of a screen row: that row sums the live ones
    2-3 sigmas away, as the map does, instead of nothing (a NaN row never refined)."""
    def dead_near_row(geometry, rows):       # screen row len(rows) // 4: map row twice it
        return np.abs(geometry.across - rows[2 * (len(rows) // 4)]) > 2.05 * SIGMA_BEAM

    made = noise_search(14, dead_near_row)
    _, _, geometry, rows, _, live, _ = made
    k = len(rows) // 4
    assert (np.abs(geometry.across[live] - rows[2 * k]) < 3 * SIGMA_BEAM).any()
    screen, at = screen_and_map(*made)
    assert np.isfinite(screen[k]).all()
    assert np.allclose(screen[k], at[k], atol=0.02)
