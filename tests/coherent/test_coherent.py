"""The coherent statistic of a wafer crossing: normalization, sensitivity, time slides, far."""
import numpy as np
import pytest

from so_transients.coherent.config import CoherentConfig
from so_transients.common.angles import ARCMIN
from so_transients.significance.far import SignificanceConfig
from so_transients.coherent.statistic import (
    EDGE_FRACTION, MAX_SCALE_VALUES, SHIFT_ADD_BLOCK, CrossingGeometry, coherent_map,
    edge_samples, false_alarm_rate, local_maxima, measured_scale, row_offsets, row_weights,
    time_slide_offsets
)

FS = 200.0
SIGMA_BEAM = 0.94 * ARCMIN               # f090 beam sigma
SPEED = np.radians(1.0)                  # 1 deg/s drift across the focal plane
ROW_STEP = SignificanceConfig().row_step


def wafer(n_side=24, pitch=1.3 * ARCMIN, rng=None):
    """A square grid of detectors and a drift along xi; per-detector amplitude noise."""
    grid = (np.arange(n_side) - (n_side - 1) / 2) * pitch
    xi, eta = (v.ravel() for v in np.meshgrid(grid, grid))
    geometry = CrossingGeometry.from_drift(xi, eta, [SPEED, 0.0], FS, centre=(0.0, 0.0))
    sigma = (rng or np.random.default_rng(0)).uniform(20, 60, len(xi))
    return geometry, sigma


def matched_pulse(n, centre, width):
    t = np.arange(n)
    return np.exp(-0.5 * ((t - centre) / width) ** 2)


def inject(snr, geometry, sigma, flux, t0, c):
    """A source of ``flux`` mJy passing the centre at sample ``t0`` at cross-scan ``c``:
    each detector's filtered S/N peaks at its lag with amplitude flux x beam / sigma."""
    beam = np.exp(-0.5 * ((geometry.across - c) / SIGMA_BEAM) ** 2)
    width = SIGMA_BEAM / SPEED * FS
    for d in np.flatnonzero(beam > 1e-4):
        snr[d] += flux * beam[d] / sigma[d] * matched_pulse(snr.shape[1],
                                                            t0 + geometry.lag_samples[d], width)


def test_noise_only_z_has_unit_variance():
    rng = np.random.default_rng(1)
    geometry, sigma = wafer(rng=rng)
    snr = rng.normal(size=(len(sigma), 4000))
    rows = row_offsets(geometry, SIGMA_BEAM, ROW_STEP)
    z, _ = coherent_map(snr, geometry, rows, SIGMA_BEAM, sigma, np.ones(len(sigma), bool))
    values = z[np.isfinite(z)]
    # Z is a weighted sum of unit-variance S/N divided by the weights' norm: unit variance
    # and zero mean by construction. Its ~164,000 values (41 rows x 4000 samples) are not
    # independent: shifting white noise and adding keeps it white in time (lag-1 correlation
    # measured 0.003), but neighbouring rows share detectors. With rho_k the correlation of
    # rows k apart (measured on this map: 0.86, 0.53, 0.24, 0.08, ...), the mean of N values
    # has variance sum_k rho_k / N (all lags, both signs) and the variance's estimate
    # 2 sum_k rho_k^2 / N, so std's standard error is half of that's square root:
    # 0.005 and 0.003 here. Five standard errors: a false failure < 1e-6, and a 2 %
    # error in the normalization fails.
    rho = row_correlation(z, max_lag=10)
    n = values.size
    sum_rho, sum_rho2 = 1 + 2 * rho.sum(), 1 + 2 * (rho**2).sum()
    assert abs(np.mean(values)) < 5 * np.sqrt(sum_rho / n)
    assert abs(np.std(values) - 1) < 5 * 0.5 * np.sqrt(2 * sum_rho2 / n)
    # measured_scale: 1.4826 x the MAD of every 8th value (20,000 at most: whole columns of
    # rows, so the row correlation applies). The MAD's variance is 1.36 / n for independent
    # Gaussian values (its 37 % efficiency); times sum_k |rho_k| (the larger of the two
    # correlation factors, to be safe): 0.017 here, five of which is 0.09.
    n_scale = len(values[::max(1, n // MAX_SCALE_VALUES)])
    assert abs(measured_scale(z) - 1) < 5 * np.sqrt(1.36 * (1 + 2 * np.abs(rho).sum()) / n_scale)


def row_correlation(z, max_lag):
    """Correlation of a map's finite values ``k`` rows apart, k = 1 .. max_lag."""
    out = []
    for k in range(1, max_lag + 1):
        a, b = z[k:], z[:-k]
        ok = np.isfinite(a) & np.isfinite(b)
        out.append(np.mean(a[ok] * b[ok]) / np.sqrt(np.mean(a[ok] ** 2) * np.mean(b[ok] ** 2)))
    return np.array(out)


def test_z_of_a_crossing_matches_its_expected_value_and_flux():
    rng = np.random.default_rng(2)
    geometry, sigma = wafer(rng=rng)
    rows = row_offsets(geometry, SIGMA_BEAM, ROW_STEP)
    c = rows[len(rows) // 2]                       # on a row: no position loss
    snr = rng.normal(size=(len(sigma), 4000))
    inject(snr, geometry, sigma, 150.0, 2000, c)
    z, flux = coherent_map(snr, geometry, rows, SIGMA_BEAM, sigma, np.ones(len(sigma), bool))
    beam = np.exp(-0.5 * ((geometry.across - c) / SIGMA_BEAM) ** 2)
    beam[np.abs(geometry.across - c) > 3 * SIGMA_BEAM] = 0
    expected = 150.0 * np.sqrt(np.sum((beam / sigma) ** 2))
    row = len(rows) // 2
    # the peak is Z at the source plus noise of unit variance: within 10 % of expected
    # (expected is about 27 here, so 10 % is 2.7 standard deviations of the noise)
    assert abs(z[row, 2000] - expected) < 0.1 * expected
    assert abs(flux[row, 2000] - 150.0) < 0.1 * 150.0
    peaks = local_maxima(z, 8.0, 5)
    assert (row, 2000) in set(zip(*peaks)) or np.max(np.abs(peaks[1] - 2000)) <= 1


def test_a_crossing_at_a_scan_end_is_summed_over_the_detectors_that_saw_it():
    """A source passing the wafer's centre 10 samples after the scan starts (half the wafer
    crossed it before): the map there sums the detectors crossed inside the scan, written
    out here, and reaches the Z those alone give within the noise. On noise whose last
    second is offset by 50 (which a cyclic sum would carry into the first samples) the
    scan's first positions keep unit variance."""
    rng = np.random.default_rng(4)
    geometry, sigma = wafer(rng=rng)
    rows = row_offsets(geometry, SIGMA_BEAM, ROW_STEP)
    row, t0, live = len(rows) // 2, 10, np.ones(len(sigma), bool)
    noise = rng.normal(size=(len(sigma), 4000))
    noise[:, -200:] += 50.0
    z, _ = coherent_map(noise, geometry, rows, SIGMA_BEAM, sigma, live)
    first = edge_samples(noise.shape[1], geometry.lag_samples)
    first = first[first < noise.shape[1] // 2]
    values = z[:, first][np.isfinite(z[:, first])]
    # ~40 rows x 50 samples, correlated over a few of each: the spread to about 5 %
    assert len(first) >= 40 and len(values) > 1000
    assert abs(np.std(values) - 1) < 0.15 and np.max(np.abs(values)) < 5

    snr = noise.copy()
    inject(snr, geometry, sigma, 150.0, t0, rows[row])
    z, flux = coherent_map(snr, geometry, rows, SIGMA_BEAM, sigma, live)
    weights, norm = row_weights(geometry, rows, SIGMA_BEAM, sigma, live)
    at = t0 + geometry.lag_samples
    inside = (at >= 0) & (at < snr.shape[1]) & (weights[row] > 0)
    norm2 = np.sum(weights[row, inside]**2)
    assert EDGE_FRACTION * norm[row]**2 <= norm2 < 0.7 * norm[row]**2  # part of the wafer
    terms = weights[row, inside] * snr[inside, at[inside]]
    assert z[row, t0] == pytest.approx(terms.sum() / np.sqrt(norm2))
    assert flux[row, t0] == pytest.approx(terms.sum() / norm2)
    # Z of the detectors that saw it: 150 mJy x sqrt(sum of their (beam / sigma)^2)
    expected = 150.0 * np.sqrt(norm2)
    assert abs(z[row, t0] - expected) < 4 and abs(flux[row, t0] - 150.0) < 4 * 150 / expected


def test_a_time_slide_removes_the_source_and_keeps_the_noise():
    rng = np.random.default_rng(3)
    geometry, sigma = wafer(rng=rng)
    rows = row_offsets(geometry, SIGMA_BEAM, ROW_STEP)
    snr = rng.normal(size=(len(sigma), 6000))
    inject(snr, geometry, sigma, 300.0, 3000, rows[len(rows) // 2])
    live = np.ones(len(sigma), bool)
    z, _ = coherent_map(snr, geometry, rows, SIGMA_BEAM, sigma, live)
    offsets = time_slide_offsets(len(sigma), 6000, 200, rng)
    slid, _ = coherent_map(snr, geometry, rows, SIGMA_BEAM, sigma, live, offsets=offsets)
    assert np.nanmax(z) > 40
    assert np.nanmax(slid) < 6                     # no alignment left
    assert abs(measured_scale(slid) - 1) < 0.1


def test_the_shift_and_add_is_a_weighted_sum_of_cyclically_shifted_streams():
    """Against the sum written out with np.roll, detector by detector in order (the same
    sums: bit-identical), on a scan several of the kernel's time blocks long, with slides
    past either end and a dead detector; float32 sums agree to 1e-6."""
    rng = np.random.default_rng(3)
    geometry, sigma = wafer(n_side=6, rng=rng)
    live = np.ones(len(sigma), bool)
    live[4] = False
    nsamp = 3 * SHIFT_ADD_BLOCK + 123
    snr = rng.standard_normal((len(sigma), nsamp)).astype(np.float32)
    rows = row_offsets(geometry, SIGMA_BEAM, ROW_STEP)
    offsets = rng.integers(-nsamp, 2 * nsamp, len(sigma))
    z, _ = coherent_map(snr, geometry, rows, SIGMA_BEAM, sigma, live, offsets)
    weights, norm = row_weights(geometry, rows, SIGMA_BEAM, sigma, live)
    shifts = geometry.lag_samples + offsets
    expected = np.array([sum(w[d] * np.roll(snr[d].astype(float), -shifts[d])
                             for d in np.flatnonzero(w)) for w in weights]) / norm[:, None]
    assert np.array_equal(z, expected)
    z32, _ = coherent_map(snr, geometry, rows, SIGMA_BEAM, sigma, live, offsets,
                          dtype=np.float32)
    assert z32.dtype == np.float32 and np.max(np.abs(z32 - z)) < 1e-5


def test_a_glitch_on_every_detector_at_one_instant_stays_incoherent():
    """A cosmic-ray hit seen by every detector at the same sample lines up only along one
    column of the focal plane: its Z is a small fraction of a source's of the same
    per-detector amplitude."""
    rng = np.random.default_rng(4)
    geometry, sigma = wafer(rng=rng)
    rows = row_offsets(geometry, SIGMA_BEAM, ROW_STEP)
    live = np.ones(len(sigma), bool)
    glitch = rng.normal(size=(len(sigma), 4000))
    width = SIGMA_BEAM / SPEED * FS
    glitch += 5.0 * matched_pulse(4000, 2000, width)[None, :]     # S/N 5 on every detector
    z_glitch, _ = coherent_map(glitch, geometry, rows, SIGMA_BEAM, sigma, live)
    source = rng.normal(size=(len(sigma), 4000))
    inject(source, geometry, sigma, 5.0 * np.median(sigma), 2000, rows[len(rows) // 2])
    z_source, _ = coherent_map(source, geometry, rows, SIGMA_BEAM, sigma, live)
    assert np.nanmax(z_glitch) < 0.5 * np.nanmax(z_source)


def test_false_alarm_rate_decreases_with_the_statistic():
    background = np.random.default_rng(5).normal(size=1000) + 4
    far = false_alarm_rate([3.0, 4.0, 5.0, 6.0, 10.0], background, 100.0)
    assert np.all(np.diff(far) <= 0) and far[0] > far[2] > 0
    assert far[-1] == 0.5 / 100.0                  # beyond every background peak: a bound
    assert far[1] == np.sum(background >= 4.0) / 100.0


@pytest.mark.parametrize("groups, gate, crossing, leaks", [
    (0, 8.0, 3000, False), (8, 8.0, 3000, False), (8, 1e6, 3000, True),
    (8, 8.0, 5990, False), (8, 8.0, 20, False)])
def test_a_bright_source_does_not_leak_into_its_own_background(groups, gate, crossing, leaks):
    """A time slide scatters a bright source's detector spikes: without leaving out the
    maxima one detector makes, a 3 Jy source filled the background with Z >= 7 peaks.
    Slid in 8 groups, each group's part of it is a coherent Z of its own (dozens of parts
    at Z >= 7 in 10 slides) unless the source is gated out of what is slid first, also
    when it crosses at either end of the scan (where the data's map is NaN)."""
    from so_transients.significance.far import SignificanceConfig, scan_maps

    rng = np.random.default_rng(6)
    geometry, sigma = wafer(rng=rng)
    live = np.ones(len(sigma), bool)
    cfg = SignificanceConfig(n_slides=10, min_slide_s=1.0, slide_groups=groups,
                             slide_gate=gate)
    noise = rng.normal(size=(len(sigma), 6000))
    vetoes = CoherentConfig().vetoes
    quiet = scan_maps(noise, geometry, SIGMA_BEAM, sigma, live, 0, cfg, vetoes,
                      np.random.default_rng(1))
    bright = noise.copy()
    inject(bright, geometry, sigma, 3000.0, crossing, 0.0)
    loud = scan_maps(bright, geometry, SIGMA_BEAM, sigma, live, 0, cfg, vetoes,
                     np.random.default_rng(1))
    n_quiet = np.sum(np.asarray(quiet.background) >= 7)
    n_loud = np.sum(np.asarray(loud.background) >= 7)
    # noise alone: none expected at Z >= 7 in 10 slides of 30 s; allow a few from the source
    assert n_quiet <= 2
    assert (n_loud > n_quiet + 20) if leaks else (n_loud <= n_quiet + 5), (n_quiet, n_loud)
    if crossing == 3000:                                 # the source itself is there
        assert np.nanmax(loud.z) > 100


def test_window_max_is_the_maximum_filter_at_the_positions():
    """As ``scipy.ndimage.maximum_filter`` (NaN as -inf, edges clipped) read at the given
    positions."""
    from scipy import ndimage
    from so_transients.coherent.statistic import window_max
    rng = np.random.default_rng(4)
    z = rng.normal(size=(9, 300))
    z[:, :7] = np.nan
    z[3, 100:140] = np.nan
    z[:, 200:260] = np.nan                       # a window with nothing finite: -inf
    rows, samples = rng.integers(0, 9, 50), rng.integers(0, 300, 50)
    rows[:3], samples[:3] = [0, 8, 4], [0, 299, 230]
    full = ndimage.maximum_filter(np.nan_to_num(z, nan=-np.inf), size=(5, 41), mode="nearest")
    out = window_max(z, rows, samples, 2, 20)
    assert np.array_equal(out, full[rows, samples]) and out[2] == -np.inf
