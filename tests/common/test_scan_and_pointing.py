"""The constant-elevation scan and the exact pointing helpers, checked against so3g."""
import numpy as np
import pytest

from so_transients.common import pointing
from so_transients.sim.scan import ScanPattern, boresight, constant_velocity_mask

T0 = 1_700_000_000.0
FS = 220.0


@pytest.fixture(scope="module")
def scan():
    pattern = ScanPattern()
    t_rel = np.arange(0, 400, 1 / FS)
    az, el, sweep = boresight(t_rel, pattern)
    q = pointing.boresight_quats(T0 + t_rel, az, el, np.zeros_like(az))
    return pattern, t_rel, az, el, sweep, q


def test_on_sky_speed_in_constant_velocity_parts(scan):
    pattern, t_rel, az, el, _, q = scan
    ra, dec = pointing.radec_of_samples(q, [0.0], [0.0], np.zeros(len(t_rel), int),
                                        np.arange(len(t_rel)))
    step = 22   # 0.1 s
    cos_d = (np.sin(dec[:-step]) * np.sin(dec[step:])
             + np.cos(dec[:-step]) * np.cos(dec[step:]) * np.cos(ra[step:] - ra[:-step]))
    speed = np.degrees(np.arccos(np.clip(cos_d, -1, 1))) / (step / FS)
    cv = constant_velocity_mask(t_rel[:-step], pattern) & constant_velocity_mask(t_rel[step:], pattern)
    assert np.all(np.abs(speed[cv] - 1.0) < 0.02)


def test_sweeps_and_turnarounds(scan):
    pattern, t_rel, az, _, sweep, _ = scan
    v = np.gradient(np.degrees(az), 1 / FS)
    reversals = np.flatnonzero(np.diff(np.sign(v[np.abs(v) > 1e-6])) != 0)
    assert len(reversals) == 4                       # 400 s of 90 s sweeps
    assert 80 <= pattern.sweep_time <= 100
    # the turnaround decelerates at the configured acceleration, never faster
    acc = np.abs(np.gradient(v, 1 / FS))[2:-2]
    assert acc.max() < pattern.accel * 1.05
    assert np.isclose(np.degrees(np.ptp(az)), pattern.az_throw, rtol=1e-3)
    assert np.all(np.diff(sweep) >= 0) and sweep[-1] == 4


def test_source_in_focal_plane_inverts_radec(scan):
    *_, q = scan
    xi, eta = np.radians([0.3, -1.2]), np.radians([-0.4, 0.9])
    samples = [1000, 50000]
    for k in range(2):
        ra, dec = pointing.radec_of_samples(q, xi, eta, [k], [samples[k]])
        sx, se = pointing.source_in_focal_plane(q[samples[k]:samples[k] + 1], ra[0], dec[0])
        assert np.allclose([sx[0], se[0]], [xi[k], eta[k]], atol=1e-10)


def test_angular_distance_matches_spherical_formula(scan):
    *_, q = scan
    xi = np.radians([0.5, 0.52, -1.5])
    eta = np.radians([0.2, 0.23, 1.0])
    ra, dec = pointing.radec_of_samples(q, xi, eta, [0, 1, 2], [7, 7, 7])
    for i, j in ((0, 1), (0, 2)):
        expect = np.arccos(np.sin(dec[i]) * np.sin(dec[j])
                           + np.cos(dec[i]) * np.cos(dec[j]) * np.cos(ra[i] - ra[j]))
        got = pointing.angular_distance_xieta(xi[i], eta[i], xi[j], eta[j])
        assert np.isclose(got, expect, rtol=1e-9, atol=1e-12)


def test_horizon_offsets_match_full_pointing(scan):
    """A detector's az/el from horizon_offsets, pointed as a boresight, sees the same sky."""
    _, t_rel, az, el, _, q = scan
    xi, eta = np.radians([1.1]), np.radians([-0.7])
    daz, el_det = pointing.horizon_offsets(xi, eta, el[0])
    k = 12345
    ra_det, dec_det = pointing.radec_of_samples(q, xi, eta, [0], [k])
    q_as_bore = pointing.boresight_quats(T0 + t_rel[k:k + 1], az[k:k + 1] + daz, el_det, [0.0])
    ra_b, dec_b = pointing.radec_of_samples(q_as_bore, [0.0], [0.0], [0], [0])
    sep = np.hypot((ra_b - ra_det) * np.cos(dec_det), dec_b - dec_det)
    assert sep[0] < np.radians(1 / 3600)


def test_bad_scan_parameters():
    with pytest.raises(ValueError, match="elevation"):
        ScanPattern(el=95)
    with pytest.raises(ValueError, match="shorter than one turnaround"):
        ScanPattern(sweep_time=2.0)


@pytest.mark.parametrize("xi0, reach_deg", [(0.5, 1.0), (0.5, 0.05), (25.0, 1.0)])
def test_source_near_equals_tracking_every_sample(scan, xi0, reach_deg):
    """Coarse-to-fine tracking finds exactly the samples a full track does, turnarounds included."""
    *_, q = scan
    ra, dec = pointing.radec_of_samples(q, np.radians([xi0]), [0.0], [0], [30000])
    reach = np.radians(reach_deg)
    xi, eta = pointing.source_in_focal_plane(q, ra[0], dec[0])
    expect = np.flatnonzero(pointing.angular_distance_xieta(xi, eta, 0.0, 0.0) < reach)
    samples, sxi, seta = pointing.source_near(q, ra[0], dec[0], (0.0, 0.0), reach)
    assert np.array_equal(samples, expect)
    assert np.array_equal(sxi, xi[expect]) and np.array_equal(seta, eta[expect])
    assert (len(expect) > 0) == (xi0 < 10)


def test_crossing_times_from_a_given_track_equal_computing_it(scan):
    """The injections pass the track they already have (a wider reach); same crossings."""
    from so_transients.common.flare_model import active_window
    from so_transients.campaign.matching import crossing_times
    from so_transients.sim.sources import BEAM_REACH_SIGMA
    *_, q = scan
    t = T0 + np.arange(len(q)) / FS
    ra, dec = pointing.radec_of_samples(q, [0.004], [0.001], [0], [30000])
    flare = dict(ra=ra[0], dec=dec[0], t_peak=t[30000], s_peak=300.0, t_rise=130.0,
                 t_decay=130.0, eta_rise=1.0, eta_decay=1.0)
    rng = np.random.default_rng(3)
    xi, eta = rng.uniform(-0.006, 0.006, (2, 300))
    fwhm = np.radians(2.2 / 60)
    centre = (xi.mean(), eta.mean())
    reach = np.hypot(xi - centre[0], eta - centre[1]).max() + BEAM_REACH_SIGMA * fwhm / 2.355
    lo, hi = np.searchsorted(t, active_window(flare["t_peak"], 130.0))
    near, sxi, seta = pointing.source_near(q[lo:hi], ra[0], dec[0], centre, reach)
    alone = crossing_times(t, q, xi, eta, flare, fwhm)
    given = crossing_times(t, q, xi, eta, flare, fwhm, track=(near + lo, sxi, seta))
    assert len(alone) >= 2 and np.array_equal(alone, given)
