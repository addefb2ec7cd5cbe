"""find, cuts, fit and the catalogue storage on synthetic inputs with exact expectations."""
import numpy as np
import pytest
from sotodlib import core

from so_transients.preprocess import slot_storage
from so_transients.detect.cuts import (
    CutsConfig, apply_cuts, dominant_orientation_fraction, time_order
)
from so_transients.detect.find import FindConfig, find_candidates, scan_segments
from so_transients.detect.error_scale import null_scatter
from so_transients.detect.fit import Track, fit_candidate
from so_transients.common.angles import ARCMIN

PITCH = 1.574 * ARCMIN
SPEED = np.radians(1.0)          # 1 deg/s


# ------------------------------------------------------------------------------ find

def test_scan_segments_split_at_turnarounds_and_know_their_direction():
    az = np.concatenate([np.linspace(0, 1, 10), np.ones(3), np.linspace(1, 0, 10)])
    in_ta = np.zeros(23, bool)
    in_ta[10:13] = True
    scan, directions = scan_segments(in_ta, az)
    assert list(scan) == [0] * 10 + [-1] * 3 + [1] * 10
    assert list(directions) == [1, -1]


def _sky_grid(ndet, nsamp):
    """Detector d at sample s looks at (ra, dec) = (s * step, d * PITCH): rows of the sky."""
    step = SPEED / 220
    return lambda d, s: (np.asarray(s) * step, np.asarray(d) * PITCH)


def test_dbscan_groups_a_source_and_ignores_scattered_noise():
    ndet, nsamp = 40, 4000
    snr = np.zeros((ndet, nsamp), np.float32)
    snr[10:16, 2000:2004] = 6.0           # 6 adjacent detectors, same sky spot: 24 samples
    snr[3, 500:504] = 5.0                 # an isolated excursion: 4 samples
    snr[30, 3500:3503] = 5.0
    t = np.arange(nsamp) / 220.0
    scan = np.zeros(nsamp, int)
    cands, hits = find_candidates(snr, t, scan, np.array([1]), _sky_grid(ndet, nsamp),
                                  eps=1.2 * PITCH, cfg=FindConfig())
    assert len(cands["scan"]) == 1
    assert cands["n_samples"][0] == 24 and cands["n_dets"][0] == 6
    assert set(hits["det"]) == set(range(10, 16))
    assert np.isclose(cands["cluster_dec"][0], 12.5 * PITCH)


def test_clusters_of_ten_samples_or_fewer_are_dropped():
    snr = np.zeros((40, 4000), np.float32)
    snr[10:15, 2000:2002] = 6.0           # 10 samples: not "more than 10"
    cands, _ = find_candidates(snr, np.arange(4000) / 220.0, np.zeros(4000, int),
                               np.array([1]), _sky_grid(40, 4000), eps=1.2 * PITCH,
                               cfg=FindConfig())
    assert len(cands["scan"]) == 0


def test_samples_in_turnarounds_are_not_searched():
    snr = np.zeros((40, 4000), np.float32)
    snr[10:16, 2000:2004] = 6.0
    scan = np.zeros(4000, int)
    scan[1990:2010] = -1
    cands, _ = find_candidates(snr, np.arange(4000) / 220.0, scan, np.array([1]),
                               _sky_grid(40, 4000), eps=1.2 * PITCH, cfg=FindConfig())
    assert len(cands["scan"]) == 0


def test_candidate_cap_keeps_the_brightest():
    snr = np.zeros((40, 8000), np.float32)
    for k, start in enumerate(range(500, 7500, 1000)):
        snr[10:16, start:start + 4] = 4.0 + k
    cands, hits = find_candidates(snr, np.arange(8000) / 220.0, np.zeros(8000, int),
                                  np.array([1]), _sky_grid(40, 8000), eps=1.2 * PITCH,
                                  cfg=FindConfig(max_candidates=3))
    assert sorted(cands["snr_max"]) == [8.0, 9.0, 10.0]
    assert set(hits["cand"]) == {0, 1, 2}


# ------------------------------------------------------------------------------ cuts

def _row_of_detectors(n, across=0.0):
    xi = np.arange(n) * PITCH
    return xi, np.full(n, across), np.tile([0.0, np.pi / 2], n)[:n]


def _candidate(dets, samps, snr=5.0):
    hits = {"cand": np.zeros(len(dets), int), "det": np.asarray(dets),
            "samp": np.asarray(samps), "snr": np.full(len(dets), snr)}
    cands = {"scan": np.zeros(1, int), "cluster_ra": np.zeros(1), "cluster_dec": np.zeros(1)}
    return cands, hits


def test_a_drifting_source_passes_every_cut():
    xi, eta, gamma = _row_of_detectors(8)
    t = np.arange(10000) / 220.0
    samps = 2000 + np.round(xi / SPEED * 220).astype(int)     # hit in drift order
    cands, hits = _candidate(range(8), samps)
    out = apply_cuts(cands, hits, xi, eta, gamma, t, np.array([[SPEED, 0.0]]), PITCH,
                     CutsConfig())
    assert out["passed"][0] and out["cut_reason"][0] == ""
    assert np.isclose(out["aspect_ratio"][0], 8.0)
    assert out["time_rms"][0] < 0.005


def test_a_glitch_hitting_many_detectors_at_one_instant_is_rejected():
    xi, eta, gamma = _row_of_detectors(12)
    cands, hits = _candidate(range(12), np.full(12, 3000))   # all at the same sample
    out = apply_cuts(cands, hits, xi, eta, gamma, np.arange(10000) / 220.0,
                     np.array([[SPEED, 0.0]]), PITCH, CutsConfig())
    assert not out["passed"][0] and out["cut_reason"][0] == "time_order"


def test_too_few_detectors_and_cross_scan_lines_are_rejected():
    xi, eta, gamma = _row_of_detectors(4)
    samps = 2000 + np.round(xi / SPEED * 220).astype(int)
    cands, hits = _candidate(range(4), samps)
    t = np.arange(10000) / 220.0
    out = apply_cuts(cands, hits, xi, eta, gamma, t, np.array([[SPEED, 0.0]]), PITCH,
                     CutsConfig())
    assert out["cut_reason"][0] == "n_dets"
    # the same detectors, but the source drifts across the row instead of along it
    xi2, eta2 = eta, xi
    cands, hits = _candidate(range(4), np.full(4, 2000))
    out = apply_cuts(cands, hits, xi2, eta2, gamma, t, np.array([[SPEED, 0.0]]), PITCH,
                     CutsConfig(), min_dets=3)
    assert out["cut_reason"][0] == "aspect_ratio"


def test_known_sources_are_masked():
    xi, eta, gamma = _row_of_detectors(8)
    samps = 2000 + np.round(xi / SPEED * 220).astype(int)
    cands, hits = _candidate(range(8), samps)
    cands["cluster_ra"][0], cands["cluster_dec"][0] = 1.0, -0.5
    args = (cands, hits, xi, eta, gamma, np.arange(10000) / 220.0, np.array([[SPEED, 0.0]]),
            PITCH, CutsConfig())
    inside = apply_cuts(*args, known=(np.array([1.0 + 0.5 * ARCMIN / np.cos(0.5)]),
                                        np.array([-0.5])), mask_radius=1.32 * ARCMIN)
    outside = apply_cuts(*args, known=(np.array([1.0 + 2 * ARCMIN / np.cos(0.5)]),
                                         np.array([-0.5])), mask_radius=1.32 * ARCMIN)
    assert inside["cut_reason"][0] == "known_source"
    assert outside["passed"][0]


def test_polarization_flag():
    assert dominant_orientation_fraction(np.radians([10, 190, 15, 100])) == 0.75
    assert dominant_orientation_fraction(np.radians([0, 90, 0, 90])) == 0.5
    passes, r_drift, r_inst = time_order(np.array([0.0, 0.1, 0.2]), np.array([0.0, 1.0, 2.0]),
                                         10.0, 0.02)
    assert passes and r_drift == 0.0 and r_inst > 0


# ------------------------------------------------------------------------------ fit

def _gaussian_track(nt=221, fs=220.0, sigma=0.934 * ARCMIN):
    t = (np.arange(nt) - nt // 2) / fs
    lags = np.arange(-220, 221) / fs
    sigma_t = sigma / SPEED
    response = np.exp(-0.25 * (lags / sigma_t) ** 2)           # white-noise matched response
    return Track(xi=SPEED * t, eta=np.zeros(nt), along=np.array([1.0, 0.0]), speed=SPEED,
                 sigma=sigma, lags=lags, response=response), t


def test_fit_recovers_amplitude_and_position_exactly_without_noise():
    track, _ = _gaussian_track()
    det_xi = np.repeat(np.arange(-10, 11) * PITCH, 3)
    det_eta = np.tile([-PITCH, 0.0, PITCH], 21) * 0.87
    from so_transients.detect.fit import beam_shape
    truth = dict(a0=800.0, dxi=0.2 * ARCMIN, deta=-0.3 * ARCMIN, c=5.0)
    amp = truth["a0"] * beam_shape(track, det_xi, det_eta, truth["dxi"], truth["deta"]) + truth["c"]
    res = fit_candidate(track, det_xi, det_eta, amp, np.full(len(det_xi), 100.0))
    assert res["fit_ok"]
    # the fit stops within tol_chi2 = 1e-3 of the minimum: every parameter is then within
    # sqrt(1e-3) = 0.032 of its error of the truth (the noise-free minimum)
    for key, true in [("flux", "a0"), ("offset", "c"), ("dxi", "dxi"), ("deta", "deta")]:
        assert abs(res[key] - truth[true]) <= 0.035 * res[f"{key}_err"], key
    assert res["dxi_err"] < 0.1 * ARCMIN       # a precise fit: the bound above is tight


def test_fit_errors_match_the_scatter_of_repeated_noise_fits():
    rng = np.random.default_rng(0)
    track, _ = _gaussian_track()
    det_xi = np.repeat(np.arange(-10, 11) * PITCH, 2)
    det_eta = np.tile([0.0, 0.87 * PITCH], 21)
    from so_transients.detect.fit import beam_shape
    model = 300.0 * beam_shape(track, det_xi, det_eta)
    fluxes, errors = [], []
    for _ in range(60):
        amp = model + rng.normal(0, 100.0, model.shape)       # independent samples
        res = fit_candidate(track, det_xi, det_eta, amp, np.full(len(det_xi), 100.0))
        fluxes.append(res["flux"])
        errors.append(res["flux_err"])
    # 60 fits: the sample std is known to 9 %; allow 3 standard errors
    assert abs(np.std(fluxes) / np.median(errors) - 1) < 0.27
    assert abs(np.mean(fluxes) - 300.0) < 3 * np.median(errors) / np.sqrt(60)
    scale = null_scatter([(track, det_xi, det_eta, rng.normal(0, 100.0, model.shape),
                           np.full(len(det_xi), 100.0)) for _ in range(40)])
    assert 0.6 < scale < 1.4        # independent noise: the measured scale is ~1 (MAD of 40)


def test_a_glitch_residue_fails_the_peak_ratio_and_a_bright_source_passes():
    """A source crossing 60 detectors at S/N 4 each is fitted at S/N ~ 4 sqrt(60) / 1.3 ~ 24
    (a ratio of 0.17); a glitch hitting one detector at S/N 40 beside a noise cluster
    fitted at S/N 5.5 has a ratio of 7."""
    from so_transients.detect.fit import beam_shape
    from so_transients.detect.fit_candidates import peak_ratio_ok

    track, _ = _gaussian_track()
    det_xi = np.repeat(np.arange(-10, 11) * PITCH, 3)
    det_eta = np.tile([-PITCH, 0.0, PITCH], 21) * 0.87
    amp = 400.0 * beam_shape(track, det_xi, det_eta)
    res = fit_candidate(track, det_xi, det_eta, amp, np.full(len(det_xi), 100.0),
                        inflation=1.3)
    ok = peak_ratio_ok([amp.max() / 100.0, 40.0, 40.0], [res["snr_fit"], 5.5, np.nan], 3.0)
    assert list(ok) == [True, False, True]             # an unfitted candidate is not judged
    assert peak_ratio_ok([40.0], [5.5], None).all()    # off by default


# ------------------------------------------------------------------------------ storage

def test_catalogue_slots_survive_concatenation_of_groups():
    def group(names, n_cand):
        aman = core.AxisManager(core.LabelAxis("dets", names))
        cols = {"flux": np.arange(n_cand) * 10.0, "band": np.array(["f090"] * n_cand)}
        return slot_storage.pack(aman, cols, preferred_rows=np.zeros(n_cand, int), n_slots=2)
    a = group(["a0", "a1", "a2"], 5)        # 5 candidates all peaking on a0: spill over
    b = group(["b0", "b1"], 1)
    both = core.AxisManager.concatenate([a, b], axis="dets")
    rows = slot_storage.unpack(both)
    assert sorted(rows["flux"]) == [0.0, 0.0, 10.0, 20.0, 30.0, 40.0]
    assert list(rows["det"]).count("a0") == 2 and "b0" in rows["det"]
    with pytest.raises(ValueError, match="do not fit"):
        group(["x"], 3)


def test_a_null_fits_one_pass_equals_the_full_fits_amplitude():
    """``null_ratio`` (one compiled pass: 2000 of them set paper mode's error scale) is the
    amplitude fit of the beam model a full fit builds, with invalid samples (zero amplitude,
    a dead detector) and samples beyond the response's reach left out alike; and the numpy
    path (non-uniform lags) gives the same."""
    from so_transients.detect.fit import _beam_samples, null_ratio

    rng = np.random.default_rng(4)
    track, _ = _gaussian_track()
    det_xi = rng.uniform(-30, 30, 200) * PITCH
    det_eta = rng.uniform(-3, 3, 200) * PITCH
    amp = rng.normal(0, 50, (200, len(track.xi))).astype(np.float32)
    amp[:, 100:105] = 0.0                          # masked samples
    sigma_amp = rng.uniform(40, 60, 200)
    sigma_amp[7] = 0.0                             # a dead detector
    window = (track, det_xi, det_eta, amp, sigma_amp)
    beam, ok = _beam_samples(*window)
    assert 0 < ok.sum() < ok.size and not ok[7].any()
    a, err = beam.amplitude()
    assert null_ratio(window, 1.3) == pytest.approx(a / (err * 1.3), rel=1e-9)
    uneven = Track(track.xi, track.eta, track.along, track.speed, track.sigma,
                   track.lags * (1 + 1e-3 * (track.lags > 0)), track.response)
    beam, _ = _beam_samples(uneven, *window[1:])
    assert beam.geom is None
    a, err = beam.amplitude()
    assert null_ratio((uneven, *window[1:])) == pytest.approx(a / err, rel=1e-12)
    nothing = np.zeros_like(amp)
    assert np.isnan(null_ratio((track, det_xi, det_eta, nothing, sigma_amp)))


def test_compiled_normal_equations_equal_the_numpy_ones():
    """The fit's one-pass kernel (uniform lags) and the numpy spline + Jacobian path agree."""
    from so_transients.detect.fit import _BeamModel

    rng = np.random.default_rng(0)
    lags = np.arange(-220, 221) / 220.0
    response = np.exp(-0.5 * (lags / 0.016) ** 2) - 0.1 * np.exp(-0.5 * (lags / 0.2) ** 2)
    track = Track(np.linspace(-1e-3, 1e-3, 50), np.zeros(50), np.array([0.8, 0.6]), 0.0175,
                  2.7e-4, lags, response)
    along0, across0 = rng.uniform(-4e-3, 4e-3, 5000), rng.uniform(-2e-3, 2e-3, 5000)
    y, sigma = rng.normal(0, 1, 5000), rng.uniform(0.5, 2, 5000)
    fast = _BeamModel(track, along0, across0, y, sigma)
    slow = _BeamModel(track, along0, across0, y, sigma)
    slow.geom = None
    assert fast.geom is not None and fast.geom[4] == pytest.approx(220.0)
    for p in [(1.0, 0.0, 0.0, 0.0), (2.0, 1e-4, -5e-5, 3.0), (1.0, 4e-3, 0.0, 0.0)]:
        (cf, af, bf), (cs, as_, bs) = fast.normal_equations(p), slow.normal_equations(p)
        assert cf == pytest.approx(cs, rel=1e-10)
        assert np.allclose(af, as_, rtol=0, atol=1e-10 * np.abs(as_).max())
        assert np.allclose(bf, bs, rtol=0, atol=1e-10 * np.abs(bs).max())
    a, err = fast.amplitude()
    shape = fast.model((1.0, 0.0, 0.0, 0.0))
    w = sigma**-2
    assert a == pytest.approx(np.sum(w * shape * y) / np.sum(w * shape**2), rel=1e-10)
    assert err == pytest.approx(np.sum(w * shape**2) ** -0.5, rel=1e-10)

