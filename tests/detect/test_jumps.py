"""Readout jumps: found at their sample and height, removed, and never confused with a source
crossing or a cosmic ray, so that removing them cannot erase a source."""
import numpy as np
import pytest

from so_transients.detect.common_mode import ExcursionConfig, mask_excursions
from so_transients.detect.jumps import JumpConfig, find_jumps, remove_common_jumps, remove_jumps
from so_transients.detect.matched_filter import FilterConfig, matched_filter

FS = 220.0
N = 66000                  # 5 minutes
SIGMA = 1600.0             # mJy per sample: an f090 detector's white noise
WINDOW = 2.0


def noise(rng, ndet=1):
    """White noise plus a slow random-walk drift (atmosphere left after the common modes)."""
    x = rng.normal(0, SIGMA, (ndet, N))
    x += np.cumsum(rng.normal(0, 2.0, (ndet, N)), axis=1)
    return x.astype(np.float32)


def bump(peak, t0, sigma_t):
    t = np.arange(N) / FS
    return (peak * np.exp(-0.5 * ((t - t0) / sigma_t) ** 2)).astype(np.float32)


@pytest.mark.parametrize("height", [5000.0, -5000.0, 2500.0])
def test_a_jump_is_found_at_its_sample_and_height(height):
    rng = np.random.default_rng(int(abs(height)) + (height < 0))
    x = noise(rng)[0]
    x[30000:] += height
    (sample, found), = find_jumps(x, FS, WINDOW)
    # the height is a difference of two medians of W = 2 s (441 samples) each: the error of a
    # median of Gaussian noise is 1.2533 sigma / sqrt(W), so sqrt(2) x that = 134 mJy; 4 sigma
    err = np.sqrt(2) * 1.2533 * SIGMA / np.sqrt(WINDOW * FS)
    assert abs(found - height) < 4 * err
    # the CUSUM split: within a few samples for a step of several sigma per sample
    assert abs(sample - 30000) <= (3 if abs(height) > 2 * SIGMA else 20)


def test_crossings_and_cosmic_rays_are_not_jumps():
    rng = np.random.default_rng(3)
    x = noise(rng, 3)
    x[0] += bump(20000.0, 100.0, 0.04)          # a 20 Jy source crossing the beam (f090, 1 deg/s)
    x[1] += bump(50000.0, 150.0, 0.1)           # a 50 Jy planet crossing at 0.4 deg/s
    glitch = np.zeros(N, np.float32)
    glitch[40000:40010] = 50000 * np.exp(-np.arange(10) / (0.004 * FS))
    x[2] += glitch                              # a 50 Jy cosmic ray
    assert [find_jumps(row, FS, WINDOW) for row in x] == [[], [], []]


def test_removing_jumps_leaves_the_source_and_restores_the_level():
    rng = np.random.default_rng(5)
    clean = noise(rng, 2)
    clean[0] += bump(3000.0, 120.0, 0.04)
    x = clean.copy()
    x[0, 26500:] += 5000.0                      # a jump 0.5 s after the crossing
    x[1, 10000:] -= 5000.0
    counts = remove_jumps(x, FS, WINDOW)
    assert list(counts) == [1, 1]
    err = np.sqrt(2) * 1.2533 * SIGMA / np.sqrt(WINDOW * FS)
    residual = np.median(x[:, 30000:] - clean[:, 30000:], axis=1)
    assert np.all(np.abs(residual) < 4 * err)
    peak = slice(26390, 26410)
    assert np.allclose(x[0, peak], clean[0, peak])          # the crossing is untouched


def test_the_filter_sees_a_source_next_to_a_jump_as_without_it():
    """transient_filter removes jumps from its copy: a 3 Jy crossing 1 s before a 5 Jy jump on
    the same detector keeps its S/N (without removal the jump's ringing and its power in the
    PSD change it)."""
    rng = np.random.default_rng(7)
    x = noise(rng, 8)
    sigma_t = 0.934 / 60 / 1.0                 # f090 beam sigma at 1 deg/s on the sky
    for row in x:
        row += bump(3000.0, 120.0, sigma_t)
    jumped = x.copy()
    jumped[0, int(121.0 * FS):] += 5000.0
    ref = matched_filter(x, FS, sigma_t, FilterConfig())
    res = matched_filter(jumped, FS, sigma_t, FilterConfig())
    k = int(120.0 * FS)
    assert res.n_jumps[0] == 1 and not res.n_jumps[1:].any()
    # the S/N at the peak (~25 here) moves by the height error over the noise: 134 / 1600 of
    # a sample's sigma spread over the template, well under 1 in S/N
    assert abs(res.snr[0, k] - ref.snr[0, k]) < 1.0
    off = matched_filter(jumped, FS, sigma_t, FilterConfig(jump_threshold=None))
    assert abs(off.snr[0, k] - ref.snr[0, k]) > abs(res.snr[0, k] - ref.snr[0, k])


def test_jumps_under_a_common_atmosphere_are_removed_from_live_and_dead_channels():
    """Before the PCA the atmosphere (here a 10 Jy random walk common to the wafer, with 20 %
    gain scatter) hides a 5 Jy jump from a detector's own level changes; in the detector minus
    its share of the common mode it stands out. A dead channel (zeros) that carries a jump
    loses it; a 20 Jy crossing next to a jump and a cosmic ray are left as they were."""
    rng = np.random.default_rng(11)
    ndet = 40
    atmosphere = np.cumsum(rng.normal(0, 60.0, N))
    atmosphere *= 10000.0 / atmosphere.std()
    gains = rng.normal(1.0, 0.2, ndet)
    clean = noise(rng, ndet) + (gains[:, None] * atmosphere).astype(np.float32)
    clean[3] = 0.0                                  # a dead channel
    clean[5] += bump(20000.0, 100.0, 0.04)          # a 20 Jy crossing ...
    clean[7, 40000:40010] += 50000.0                # ... and a 50 Jy cosmic ray
    x = clean.copy()
    jumps = {1: (20000, 5000.0), 3: (30000, -5000.0), 5: (int(101.0 * FS), 5000.0),
             9: (50000, -5000.0)}
    for row, (sample, height) in jumps.items():
        x[row, sample:] += height
    plain = x.copy()
    assert sum(remove_jumps(plain[[1, 9]], FS, WINDOW)) == 0    # hidden by the atmosphere
    counts = remove_common_jumps(x, FS, JumpConfig(window=WINDOW))
    assert {int(r) for r in np.flatnonzero(counts)} == set(jumps) and counts.max() == 1
    # What is left of a live channel's jump: its height is measured beside an atmosphere
    # removed only as well as a gain fitted to it; over 40 seeds the rest is 50 +- 270 mJy
    # (216 +- 250 next to the crossing) and never above 740: a tenth of that would not do.
    for row in (1, 5, 9):
        sample = jumps[row][0] + 10
        assert abs(np.median(x[row, sample:] - clean[row, sample:])) < 1000.0, row
    # the dead channel: back to zero but for the gain its own jump gives it (40 seeds: at
    # most 0.6 % of the jump)
    assert np.abs(x[3]).max() < 0.01 * 5000.0
    peak = slice(int(100.0 * FS) - 10, int(100.0 * FS) + 10)
    assert np.array_equal(x[5, peak], clean[5, peak])   # the crossing, before its jump
    others = [r for r in range(ndet) if r not in jumps]
    assert np.array_equal(x[others], clean[others])  # the crossing of row 5 aside, nothing else


def test_a_crossing_is_hidden_from_the_pca_model_and_the_atmosphere_is_not():
    """mask_excursions replaces a bright crossing in the (low-passed) model signal by the
    detector's baseline and leaves every other sample as it was."""
    rng = np.random.default_rng(13)
    ndet = 30
    atmosphere = np.cumsum(rng.normal(0, 60.0, N))
    atmosphere *= 10000.0 / atmosphere.std()
    gains = rng.normal(1.0, 0.2, ndet)
    box = np.ones(37) / 37                          # about a 3 Hz low-pass: 263 mJy of noise
    white = np.array([np.convolve(row, box, mode="same") for row in noise(rng, ndet)])
    clean = (white + gains[:, None] * atmosphere).astype(np.float32)
    x = clean.copy()
    x[4] += bump(3000.0, 150.0, 0.1)                # a 3 Jy crossing, low-passed
    counts, limits = mask_excursions(x, FS, ExcursionConfig(threshold=5.0, buffer=0.2))
    near = slice(int(149.8 * FS), int(150.2 * FS))
    # above 5 x 263 mJy for +-0.13 s, masked with 0.2 s around: at least 0.5 s
    assert counts[4] >= int(0.5 * FS)
    # each row's limit: 5 times its spread about the baseline, which is the noise and what
    # of the atmosphere the baseline misses; the crossing went beyond its row's
    assert np.all(np.isfinite(limits) & (limits > 0.9 * 5 * 263.0)) and limits[4] < 3000.0
    assert np.abs(x[4, near] - clean[4, near]).max() < 0.3 * 3000.0
    untouched = np.ones(N, bool)
    untouched[int(149.0 * FS):int(151.0 * FS)] = False
    # 5 sigma excursions of Gaussian noise: 6e-7 of the samples, so nearly every row untouched
    assert np.mean(x[:, untouched] == clean[:, untouched]) > 0.999


def _mask_excursions_numpy(rows, sample_rate, cfg):
    """mask_excursions' per-row loop written with numpy (its former form)."""
    from numpy.lib.stride_tricks import sliding_window_view

    from so_transients.common.robust import mad_std
    from so_transients.detect.common_mode import block_medians, block_times, common_share, \
        median_last
    from so_transients.detect.spectral_ops import dilate_rows
    nrows, nsamp = rows.shape
    counts = np.zeros(nrows, int)
    n_block = max(1, int(round(cfg.block * sample_rate))) | 1
    k = max(3, int(round(cfg.window / cfg.block))) | 1
    n = nsamp // n_block
    m = block_medians(rows, n_block, cfg.chunk_dets)
    common, gain = common_share(m, np.ptp(m, axis=1) > 0)
    rest = median_last(sliding_window_view(m - gain[:, None] * common, k, axis=1))
    t_rest = block_times(n, n_block)[k // 2:n - k // 2]
    t = np.arange(nsamp)
    common_s = np.interp(t, block_times(n, n_block), common).astype(np.float32)
    grow = max(1, int(round(cfg.buffer * sample_rate)))
    for r in range(nrows):
        # float64 (numpy 2 promotes so; numpy 1 would keep float32)
        base = np.float64(gain[r]) * common_s.astype(np.float64) + np.interp(
            t, t_rest, rest[r]).astype(np.float32).astype(np.float64)
        excess = rows[r] - base
        spread = mad_std(excess[::7])
        hit = np.abs(excess) > cfg.threshold * spread if spread > 0 else np.zeros(nsamp, bool)
        hit = dilate_rows(hit[None, :], grow)[0]
        rows[r, hit] = base[hit]
        counts[r] = int(hit.sum())
    return counts


@pytest.mark.parametrize("seed", [0, 1])
def test_masking_excursions_in_one_pass_is_the_numpy_loop(seed):
    rng = np.random.default_rng(seed)
    x = noise(rng, 40) + np.cumsum(rng.normal(0, 30.0, N)).astype(np.float32)
    for _ in range(60):                 # crossings and spikes anywhere, the ends included
        d, s = rng.integers(40), rng.choice([0, 3, N - 5, int(rng.integers(N))])
        x[d, s:s + 40] += rng.uniform(5, 40) * SIGMA
    x[5] = 0.0                          # a channel recording nothing
    cfg = ExcursionConfig(threshold=5.0, buffer=0.2)
    expected, got = x.copy(), x.copy()
    counts = _mask_excursions_numpy(expected, FS, cfg)
    assert np.array_equal(mask_excursions(got, FS, cfg)[0], counts) and counts.sum() > 60 * 40
    assert np.array_equal(got, expected)
