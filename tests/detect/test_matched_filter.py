"""The matched filter on synthetic data with known answers."""
import numpy as np
import pytest

from so_transients.detect.matched_filter import (
    FilterConfig, filter_kernels, fit_error_inflation, gaussian_template_spectrum, matched_filter
)

FS = 220.0
SIGMA_T = 0.934 / 60 / 1.0            # f090 beam sigma (0.934') at 1 deg/s, in seconds
WHITE = 367.0


def red_noise(rng, ndet, nsamp, fknee=1.23, alpha=2.7):
    """White + 1/f noise with the given knee (PSD = white (1 + (fknee/f)^alpha))."""
    f = np.fft.rfftfreq(nsamp, 1 / FS)
    shape = np.sqrt(1 + (fknee / np.maximum(f, f[1])) ** alpha)
    spec = np.fft.rfft(rng.standard_normal((ndet, nsamp)), axis=1) * shape
    return (np.fft.irfft(spec, n=nsamp, axis=1) * WHITE).astype(np.float32)


def test_gaussian_crossing_in_white_noise_gives_the_analytic_snr():
    rng = np.random.default_rng(1)
    # 10 minutes: the PSD is estimated from data containing the source, which biases the
    # source's own amplitude low by its share of the noise power (~1 % here, ~9 % in 60 s)
    nsamp, ndet, amp = 600 * 220, 40, 1500.0
    t = np.arange(nsamp) / FS
    t0 = 300.0 + rng.uniform(-0.002, 0.002, ndet)
    tod = (WHITE * rng.standard_normal((ndet, nsamp))
           + amp * np.exp(-0.5 * ((t[None] - t0[:, None]) / SIGMA_T) ** 2)).astype(np.float32)
    res = matched_filter(tod, FS, SIGMA_T, FilterConfig(highpass=1.23))
    k = int(round(300.0 * FS))
    peak_snr = res.snr[:, k - 3:k + 4].max(axis=1)
    # optimal (no high-pass) matched filter in white noise: SNR^2 = sum(s_n^2) / sigma^2
    optimal = amp / WHITE * np.sqrt(SIGMA_T * np.sqrt(np.pi) * FS)
    assert abs(np.mean(peak_snr) / optimal - 1) < 0.10
    # the band-limited filter's own expectation: sum(B T^2) / sqrt(N sum(B^2 T^2))
    nfft = res.nfft
    f = np.fft.rfftfreq(nfft, 1 / FS)
    tmpl = gaussian_template_spectrum(nfft, FS, SIGMA_T)
    b = 1 / np.sqrt(1 + (1.23 / np.maximum(f, 1e-9)) ** 8)
    w = np.where((f == 0) | (f == f[-1]), 1.0, 2.0)
    expected = amp / WHITE * (w * b * tmpl**2).sum() / np.sqrt(nsamp * (w * b**2 * tmpl**2).sum())
    # mean over 40 detectors of (S/N + unit noise): standard error 1/sqrt(40) = 0.16
    assert abs(np.mean(peak_snr) - expected) < 4 * 1 / np.sqrt(ndet) + 0.02 * expected
    # amplitude is unbiased for a template-shaped crossing: 40 detectors with sigma_A ~ 150 mJy
    # give a mean known to 24 mJy (1.6 %); allow 4 standard errors
    at_peak = res.amplitude[:, k]
    assert abs(np.mean(at_peak) - amp) < 4 * np.mean(res.sigma_amp) / np.sqrt(ndet)
    assert np.allclose(res.noise_level, WHITE, rtol=0.03)


def test_noise_only_snr_has_unit_variance():
    rng = np.random.default_rng(2)
    tod = red_noise(rng, 30, 120 * 220)
    res = matched_filter(tod, FS, SIGMA_T, FilterConfig(highpass=1.23))
    values = res.snr[res.valid]
    # 30 x ~25k samples, correlated over ~5 samples: the variance is known to ~0.5 %
    assert abs(values.var() - 1) < 0.02
    assert abs(values.mean()) < 0.02
    # the analytic normalization agrees with the measurement: each detector's scale is a MAD
    # over ~3,500 subsampled values (relative standard error 1.17 / sqrt(n) = 2 %)
    per_det = 1.17 / np.sqrt((120 - 10) * 220 / 7)
    assert abs(np.mean(res.snr_scale) - 1) < 3 * per_det / np.sqrt(30) + 0.005
    assert np.all(np.abs(res.snr_scale - 1) < 4 * per_det)


def test_fitted_knee_recovers_the_simulated_one():
    rng = np.random.default_rng(3)
    tod = red_noise(rng, 20, 300 * 220, fknee=1.23, alpha=2.7)
    res = matched_filter(tod, FS, SIGMA_T, FilterConfig(highpass=None))
    assert abs(np.median(res.fknee) / 1.23 - 1) < 0.15


def test_edges_masked_samples_and_nans_make_no_detections():
    rng = np.random.default_rng(4)
    tod = red_noise(rng, 6, 60 * 220) + 50000.0    # big offset and drifts at the edges
    tod[:, :10] += 1e5                              # a step at the start
    tod[0, 5000:5003] = np.nan                      # not finite
    tod[1, 7000:7100] += 1e6                        # flagged junk
    mask = np.zeros(tod.shape, bool)
    mask[1, 7000:7100] = True
    res = matched_filter(tod, FS, SIGMA_T, FilterConfig(highpass=1.23, edge_buffer=5.0), mask=mask)
    assert np.all(res.snr[:, : 5 * 220] == 0) and np.all(res.snr[:, -5 * 220:] == 0)
    assert np.all(res.snr[0, 5000 - 44:5003 + 44] == 0)
    assert np.all(res.snr[1, 7000 - 44:7100 + 44] == 0)
    assert np.abs(res.snr).max() < 6
    assert np.all(np.isfinite(res.amplitude))


def test_dead_detectors_are_marked_not_fatal():
    rng = np.random.default_rng(5)
    tod = red_noise(rng, 4, 30 * 220)
    tod[2] = 0.0
    res = matched_filter(tod, FS, SIGMA_T)
    assert list(res.dead) == [False, False, True, False]
    assert np.all(res.snr[2] == 0) and not res.valid[2].any()


def test_response_kernel_and_error_inflation():
    nfft = 2**15
    psd = np.ones(nfft // 2 + 1)
    lags, response, acf = filter_kernels(nfft, FS, SIGMA_T, 1e-3, psd)
    # white noise, no high-pass: the response is the template convolved with itself
    assert np.isclose(response[len(lags) // 2], 1.0)
    assert np.allclose(response, np.exp(-0.25 * (lags / SIGMA_T) ** 2), atol=1e-3)
    assert np.allclose(acf, response, atol=1e-6)     # and the noise is correlated the same way
    # against the explicit covariance: Var(A) = R^T C R / (R^T R)^2 vs naive 1 / R^T R
    n = len(lags)
    idx = np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
    half = n // 2
    rho = np.where(idx <= half, acf[np.clip(half + idx, 0, n - 1)], 0.0)
    direct = np.sqrt(response @ rho @ response / (response @ response))
    assert np.isclose(fit_error_inflation(response, acf), direct, rtol=1e-6)
    assert direct > 1.5


def test_too_short_is_an_error():
    with pytest.raises(ValueError, match="too short"):
        matched_filter(np.zeros((2, 5), np.float32), FS, SIGMA_T)


def test_a_very_bright_source_keeps_the_filter_of_its_neighbours():
    """A 20 Jy crossing in 60 s dominates its own detectors' PSD. Its amplitude stays unbiased
    (its power cancels between filter and normalization), but the filter of those detectors
    would change shape and lose S/N; the second pass, with the source masked, restores it."""
    rng = np.random.default_rng(6)
    nsamp, ndet, amp = 60 * 220, 10, 20000.0
    t = np.arange(nsamp) / FS
    tod = (WHITE * rng.standard_normal((ndet, nsamp))
           + amp * np.exp(-0.5 * ((t[None] - 30.0) / SIGMA_T) ** 2)).astype(np.float32)
    k = int(round(30.0 * FS))
    single = matched_filter(tod, FS, SIGMA_T, FilterConfig(bright_bias=None))
    double = matched_filter(tod, FS, SIGMA_T, FilterConfig())
    lags, response, _ = filter_kernels(double.nfft, FS, SIGMA_T, 1.23,
                                       np.ones(double.nfft // 2 + 1))
    expected = response[np.searchsorted(lags, 10 / FS - 1e-9)]     # 10 samples from the peak
    shape = lambda res: np.mean(res.amplitude[:, [k - 10, k + 10]]) / amp
    # one pass: the bright detectors' filter is distorted (-0.15 here vs 0.002 expected);
    # the second pass brings it at least three times closer to the white-noise filter
    assert abs(shape(single) - expected) > 0.1
    assert abs(shape(double) - expected) < abs(shape(single) - expected) / 3
    assert np.mean(double.snr[:, k]) > 1.08 * np.mean(single.snr[:, k])
    assert abs(np.mean(double.amplitude[:, k]) / amp - 1) < 0.02
    assert np.allclose(double.noise_level, WHITE, rtol=0.05)
