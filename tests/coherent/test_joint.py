"""The joint-band statistic (so_transients.coherent.joint) and its background
(so_transients.significance.joint_far) on two bands of synthetic filtered noise."""
import numpy as np
import pytest

from so_transients.coherent.joint import (
    BandScan, band_correlation, index_coefficients, joint_map, joint_maxima
)
from so_transients.coherent.statistic import CrossingGeometry, window_max
from so_transients.common.angles import ARCMIN
from so_transients.common.robust import mad_std
from so_transients.detect.fit_candidates import joint_snr, jointly_significant
from so_transients.significance.far import SignificanceConfig
from so_transients.significance.joint_far import joint_background, joint_scan, pixel_partners

FS = 100.0
SPEED = np.deg2rad(1.0)                 # rad/s across the focal plane
BEAM = {"f090": 2.2 / 2.355 * ARCMIN, "f150": 1.4 / 2.355 * ARCMIN}
GRID = np.arange(12) * ARCMIN
XI, ETA = (a.ravel() for a in np.meshgrid(GRID, GRID))


def band_scan(band, rng, nsamp, flares=()):
    """A band's scan: smoothed white S/N (as a matched filter leaves it, unit spread per
    detector) on 144 detectors an arcminute apart, plus ``flares`` ``(sample, across,
    amplitude)``: a source crossing that row of the wafer, its centre at ``sample``, each
    detector's peak S/N ``amplitude`` times the beam across the scan."""
    geometry = CrossingGeometry.from_drift(XI, ETA, (SPEED, 0.0), FS,
                                           (float(XI.mean()), float(ETA.mean())))
    width = geometry.crossing_samples(BEAM[band])
    kernel = np.exp(-0.5 * (np.arange(-4 * width, 4 * width + 1) / width) ** 2)
    kernel /= np.sqrt(np.sum(kernel**2))
    white = rng.normal(size=(len(XI), nsamp + len(kernel) - 1))
    snr = np.array([np.convolve(x, kernel, "valid") for x in white])
    t = np.arange(nsamp)
    for sample, across, amplitude in flares:
        beam = np.exp(-0.5 * ((geometry.across - across) / BEAM[band]) ** 2)
        arrive = sample + geometry.lag_samples
        snr += amplitude * beam[:, None] * np.exp(-0.5 * ((t[None, :] - arrive[:, None])
                                                          / width) ** 2)
    return BandScan(band, snr, geometry, BEAM[band], np.ones(len(XI)))


def noise_scans(seed, n_scans=6, nsamp=6000, bands=("f090", "f150")):
    rng = np.random.default_rng(seed)
    return [(k * nsamp, [band_scan(b, rng, nsamp) for b in bands]) for k in range(n_scans)]


def test_coefficients_weigh_each_band_by_its_flux_noise_and_index():
    n = np.array([[2.0, 1.0, 0.0], [2.0, 0.0, 3.0]])       # (band, row)
    c = index_coefficients(["f090", "f150"], n, indices=[0.0, 2.0])
    assert c[0, :, 0] == pytest.approx([2 ** -0.5, 2 ** -0.5])
    ratio = (145.0 / 93.0) ** 2          # index 2 favours f150 by (nu_150 / nu_90)^2
    assert c[1, 1, 0] / c[1, 0, 0] == pytest.approx(ratio)
    # a row only one band reaches is that band's Z
    assert c[:, :, 1].ravel() == pytest.approx([1, 0, 1, 0])
    assert c[:, :, 2].ravel() == pytest.approx([0, 1, 0, 1])


def test_joint_map_is_the_best_index_and_nan_where_a_band_has_none():
    rng = np.random.default_rng(0)
    z = rng.normal(size=(2, 3, 50))
    z[1, 0, 7] = np.nan
    n = np.array([[1.0, 1.0, 1.0], [2.0, 1.0, 0.0]])
    indices = [-1.0, 0.0, 3.0]
    c = index_coefficients(["f090", "f150"], n, indices)
    j, best = joint_map(z, c)
    expected = np.einsum("abr,brt->art", c, np.nan_to_num(z))
    assert np.isnan(j[0, 7]) and best[0, 7] == -1
    ok = np.isfinite(j)
    assert j[ok] == pytest.approx(expected.max(axis=0)[ok])
    assert np.array_equal(best[ok], expected.argmax(axis=0)[ok])
    assert j[2] == pytest.approx(z[0, 2])      # f150 reaches no detector there


def correlated_scans(rng, rho, nsamp=6000):
    """Both bands' scans whose S/N share a common part on each pixel: correlation ``rho``
    (the same residual atmosphere)."""
    common = band_scan("f090", rng, nsamp).snr
    scans = []
    for b in ("f090", "f150"):
        scan = band_scan(b, rng, nsamp)
        scan.snr = np.sqrt(1 - rho) * band_scan("f090", rng, nsamp).snr + np.sqrt(rho) * common
        scans.append(scan)
    return scans


def test_bands_sharing_residual_atmosphere_are_combined_at_unit_spread():
    """Both bands' S/N share a common part (the same residual atmosphere, correlation 0.4
    here): the measured correlation of their maps recovers it, and each J_alpha is in unit
    spread with it, 1.18 (sqrt(1 + 0.4)) wide without it at equal weights."""
    rng = np.random.default_rng(8)
    rho = 0.4
    scans = correlated_scans(rng, rho)
    js = joint_scan(scans, 0, SignificanceConfig(n_slides=0), rng, indices=[0.0])
    z = np.stack([m.z for m in js.maps])
    assert band_correlation(z)[0, 1] == pytest.approx(rho, abs=0.05)
    ok = np.all(np.isfinite(z), axis=0)
    assert mad_std(js.j[ok]) == pytest.approx(1.0, abs=0.05)
    naive, _ = joint_map(z, index_coefficients(["f090", "f150"], [m.n for m in js.maps], [0.0]))
    assert mad_std(naive[ok]) == pytest.approx(np.sqrt(1 + rho), abs=0.06)


def test_one_band_alone_is_its_coherent_z():
    (first, (scan,)), = noise_scans(3, n_scans=1, nsamp=3000, bands=("f150",))
    js = joint_scan([scan], first, SignificanceConfig(n_slides=0), np.random.default_rng(0))
    ok = np.isfinite(js.j)
    assert ok.mean() > 0.9
    assert js.j[ok] == pytest.approx(js.maps[0].z[ok])
    assert np.std(js.j[ok]) == pytest.approx(1.0, abs=0.1)   # in units of its spread


@pytest.fixture(scope="module")
def backgrounds():
    """The joint and single-band backgrounds of an hour-like stretch of two bands' noise."""
    cfg = SignificanceConfig(n_slides=20, seed=1)
    joint = joint_background(noise_scans(11), cfg)
    single = {b: joint_background([(f, [s[k]]) for f, s in noise_scans(11)], cfg)
              for k, b in enumerate(("f090", "f150"))}
    return joint, single


FLARE_SEED = 5
RATE = 20.0          # false alarms per hour of the wafer (both bands): 10 per band-hour


@pytest.mark.parametrize("rate", [RATE, 10 * RATE])
def test_joint_false_alarms_on_noise_follow_their_rate(backgrounds, rate):
    """The data's own maxima above the threshold for ``rate`` number what the rate says
    over the data's live time (Poisson, 3 sigma: 2 expected at ``RATE``, from the slides;
    20 at ten times it, from the sign-inverted data)."""
    joint, single = backgrounds
    threshold = joint.threshold(rate)
    counts = []

    def visit(js):
        r, s = joint_maxima(js.scans, js.maps, js.rows, js.coefficients, js.j, js.best,
                            threshold, js.window)
        counts.append(len(r))

    joint_background(noise_scans(11), SignificanceConfig(n_slides=0), visit=visit)
    expected = rate * joint.data_hours
    assert abs(sum(counts) - expected) <= 3 * np.sqrt(expected) + 1
    # the trials over indices cost little: the joint threshold is within 0.5 of the
    # single bands' at half the rate each
    assert all(abs(threshold - s.threshold(rate / 2)) < 0.5 for s in single.values())


def test_a_flare_detected_jointly_that_neither_band_detects_alone(backgrounds):
    """Flares crossing the wafer's middle row, each band's expected Z one below its
    threshold (at half the wafer's rate), read where they cross: the joint statistic (at
    the wafer's rate) detects more of them than either band alone, and detects flares that
    neither band detects."""
    joint, single = backgrounds
    thr = {b: s.threshold(RATE / 2) for b, s in single.items()}
    thr_joint = joint.threshold(RATE)
    assert np.isfinite([thr_joint, *thr.values()]).all()
    unit = {b: unit_z(b) for b in thr}
    rng = np.random.default_rng(FLARE_SEED)
    nsamp, n_scans = 6000, 6
    samples = np.arange(500, nsamp - 499, 500)
    jointly = either = joint_only = 0
    for _ in range(n_scans):
        scans = [band_scan(b, rng, nsamp, [(s, 0.0, (thr[b] - 1.0) / unit[b])
                                           for s in samples])
                 for b in ("f090", "f150")]
        js = joint_scan(scans, 0, SignificanceConfig(n_slides=0), rng)
        row, half = int(np.argmin(np.abs(js.rows))), 2 * js.window
        for s in samples:
            j = window_max(js.j, [row], [s], 1, half)[0] >= thr_joint
            alone = any(window_max(m.z, [row], [s], 1, half)[0] >= thr[b]
                        for m, b in zip(js.maps, ("f090", "f150")))
            jointly, either, joint_only = jointly + j, either + alone, joint_only + (j and not alone)
    n = n_scans * len(samples)
    # each band's Z is about N(thr - 1, 1): above thr 16 % of the time (a little more as the
    # highest of a window), either band's ~35 %; J about sqrt(2) (thr - 1), 0.5-0.7 above
    # the joint threshold: ~70 %, ~40 % with neither band. The bounds are about 3 binomial
    # sigmas (n = 66) below those rates
    assert jointly - either >= 0.1 * n, (jointly, either, n)
    assert joint_only >= 0.15 * n, (joint_only, jointly, either, n)


def unit_z(band):
    """The Z (unnormalized, no noise) of a crossing of unit amplitude on the middle row."""
    clean = band_scan(band, np.random.default_rng(0), 1000, [(500, 0.0, 1.0)])
    clean.snr -= band_scan(band, np.random.default_rng(0), 1000).snr
    js = joint_scan([clean], 0, SignificanceConfig(n_slides=0), np.random.default_rng(0))
    return np.nanmax(js.j * js.maps[0].scale)


def test_a_pairs_fits_combine_with_their_correlation_and_detect_once():
    """Two bands' fits of S/N 3.5 at index 0: combined 3.5 sqrt(2) = 4.95 with independent
    noise, 3.5 sqrt(2 / 1.3) = 4.34 when the bands' maps correlate at 0.3; only the member
    with the higher own S/N is detected through the pair."""
    cands = dict(bandpass=np.array(["f090", "f150", "f090"]), joint_id=np.array([0, 0, -1]),
                 spectral_index=np.array([0.0, 0.0, np.nan]),
                 band_correlation=np.array([0.0, 0.0, np.nan]))
    fits = dict(flux=np.array([35.0, 35.0, 50.0]), flux_err=np.array([10.0, 10.0, 10.0]),
                fit_ok=np.array([True, True, True]))
    fits["snr_fit"] = fits["flux"] / fits["flux_err"]
    fits["snr_fit"][1] = 3.4
    assert joint_snr(cands, fits)[:2] == pytest.approx([35 / 10 * np.sqrt(2)] * 2, rel=0.02)
    assert np.isnan(joint_snr(cands, fits)[2])
    cands["band_correlation"][:2] = 0.3
    fits["snr_joint"] = joint_snr(cands, fits)
    assert fits["snr_joint"][0] == pytest.approx(3.5 * np.sqrt(2 / 1.3), rel=0.02)
    assert list(jointly_significant(cands, fits, 4.0)) == [True, False, False]
    assert not jointly_significant(cands, fits, 4.5).any()


@pytest.mark.parametrize("groups", [0, 4])
def test_slides_keep_the_bands_correlation(groups):
    """Time slides shift a pixel's two detectors alike (each detector its own offset, or
    in groups): the slides' maps of bands sharing a per-pixel common part (correlation 0.4)
    stay correlated as the data's are."""
    rng = np.random.default_rng(9)
    rho = 0.4
    scans = correlated_scans(rng, rho)
    partners = pixel_partners(scans)
    assert np.array_equal(partners[1], np.arange(len(XI)))      # the same pixels here
    js = joint_scan(scans, 0, SignificanceConfig(n_slides=2, slide_groups=groups), rng)
    assert js.slide_correlation[0, 1] == pytest.approx(rho, abs=0.06)
