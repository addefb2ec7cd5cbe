"""The fast injection path agrees with filtering the injected data in full."""
import numpy as np

from so_transients.campaign.noise_model import NoiseModel, fft_length, filtered_snr
from so_transients.detect.matched_filter import FilterConfig, matched_filter
from tests.detect.test_matched_filter import FS, SIGMA_T, red_noise


def test_windowed_injection_matches_the_full_filter():
    rng = np.random.default_rng(8)
    ndet, nsamp = 12, 600 * 220
    noise = red_noise(rng, ndet, nsamp)
    t = np.arange(nsamp) / FS
    t0 = 300.0 + 0.01 * np.arange(ndet)          # a crossing drifting across the detectors
    amp = 1200.0 * np.linspace(0.7, 1.0, ndet)   # S/N ~ 6-8 per detector
    signal = amp[:, None] * np.exp(-0.5 * ((t[None] - t0[:, None]) / SIGMA_T) ** 2)
    cfg = FilterConfig(highpass=1.23)
    full = matched_filter(noise + signal.astype(np.float32), FS, SIGMA_T, cfg)
    base = matched_filter(noise, FS, SIGMA_T, cfg)
    model = NoiseModel.from_filter(base, FS, SIGMA_T)
    lo, hi = int(290 * FS), int(310 * FS)
    fast = base.snr[:, lo:hi] + filtered_snr(model, np.arange(ndet), signal[:, lo:hi])
    slow = full.snr[:, lo:hi]
    peak = slow.max(axis=1)
    assert np.all(peak > 3)
    # the source's own power changes its detectors' PSD by ~S/N^2 / n_eff, with n_eff ~ 13 Hz x
    # 600 s: < 1 % here. The two paths agree to that level at the peak (plus the ~0.5 %
    # change of the measured S/N scale), and everywhere to a small fraction of the noise.
    bias = peak**2 / (13 * 600)
    assert np.all(np.abs(fast.max(axis=1) - peak) < peak * (bias + 0.005) + 0.03)
    assert np.max(np.abs(fast - slow)) < 0.1


def test_fft_lengths_are_the_smallest_fast_size():
    fast = sorted({m * 2**k for m in (1, 3) for k in range(16)})
    for n in range(1, 20000, 7):
        assert fft_length(n) == min(f for f in fast if f >= n)


def test_the_noise_model_refilters_the_rows_the_filter_refilters():
    """A source bright enough for the filter's second pass (S/N^2 / n_eff above bright_bias)
    is weighted by a PSD without it; the fast path decides that row by row with the n_eff the
    filter itself stored, and then agrees with the full filter where it otherwise would not."""
    rng = np.random.default_rng(3)
    ndet, nsamp = 6, 240 * 220
    noise = red_noise(rng, ndet, nsamp)
    t = np.arange(nsamp) / FS
    amp = np.array([0, 0, 3e4, 0, 700, 0])[:, None]        # rows 2 (S/N ~200) and 4 (~5)
    signal = (amp * np.exp(-0.5 * ((t[None] - 120.0) / SIGMA_T) ** 2)).astype(np.float32)
    cfg = FilterConfig(highpass=1.23)
    base = matched_filter(noise, FS, SIGMA_T, cfg)
    full = matched_filter(noise + signal, FS, SIGMA_T, cfg)
    assert np.all(np.isfinite(base.n_eff)) and np.all(base.n_eff > 1000)
    lo, hi = int(110 * FS), int(130 * FS)
    peaks = {}
    for bias in (cfg.bright_bias, None):
        model = NoiseModel.from_filter(base, FS, SIGMA_T, bright_bias=bias)
        assert np.array_equal(model.n_eff, base.n_eff)
        fast = base.snr[:, lo:hi] + filtered_snr(model, np.arange(ndet), signal[:, lo:hi])
        peaks[bias] = fast.max(axis=1)
    slow = full.snr[:, lo:hi].max(axis=1)
    assert slow[2] ** 2 / base.n_eff[2] > cfg.bright_bias > slow[4] ** 2 / base.n_eff[4]
    # the bright row: without the second pass the fast path takes the own-PSD loss (1/m of each
    # frequency, ~1 % in 4 minutes) that the full filter's second pass does not
    ratio = {bias: peaks[bias][2] / slow[2] for bias in peaks}
    assert abs(ratio[cfg.bright_bias] - 1) < 0.01
    assert abs(ratio[cfg.bright_bias] - 1) < abs(ratio[None] - 1)
    assert ratio[None] < 0.995
    # the faint row is weighted as the filter weighs it either way
    assert peaks[cfg.bright_bias][4] == peaks[None][4]
