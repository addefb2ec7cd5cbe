"""Forced photometry (so_transients.detect.forced_fit) on data made by the simulator.

The other forced-fit tests build their data with the fit's own beam function. Here the
simulator makes the time-ordered data (its own beam, pointing per sample, flux per sample from
the light curve, white noise), ``transient_filter`` runs in process as in the site pipeline,
and the forced fit measures the true positions from the simulator's truth tables at every
crossing, as ``so-transients events`` does (``FitInputs.from_aman``, ``group_crossings`` with a
reach of 3 beam sigmas, ``measure_error_scales``, ``measure_crossings``).

Two effects of the filter, both derived below and both seen:

* the template is one Gaussian of width beam sigma / the *boresight's* sky speed, but a source
  crosses w16 (1.2 deg below the boresight, at elevation 50 deg) at the sky speed of its own
  elevation, 2-3 % faster: its crossing is narrower than the template, and the fitted flux is
  low by :func:`template_factor` (1.5-2.3 % here; measured 2.0 +- 0.2 % on 5 Jy sources, 1.8 %
  predicted). The truth is compared with that factor applied;
* the filtered crossing of a source has negative sidelobes along the scan: a forced fit 10'
  along the scan from a source measures -16 % of its flux (:func:`sidelobe_leak`, from the
  filter's response alone), while 10' across the scan it measures nothing.
"""
import numpy as np
import pytest
from astropy import units as u
from astropy.coordinates import SkyCoord
from scipy import stats

from so_transients.common import pointing
from so_transients.common.angles import ARCMIN
from so_transients.common.flare_model import flare_flux
from so_transients.common.scan_geometry import drift_velocity
from so_transients.detect.find import FindConfig, group_scans
from so_transients.detect.error_scale import Sources, measure_error_scales
from so_transients.detect.fit import FitConfig, FitInputs
from so_transients.detect.forced_fit import PhotometryConfig, group_crossings, measure_crossings

from tests.conftest import load_group, run_sim, run_steps

FILTER = [{"name": "transient_filter", "process": {}, "calc": True, "save": True}]
W16 = {"tubes": ["i1"], "wafers": ["w16"], "bands": ["f090"]}
#: 0.7-1.5 Jy flares (S/N 25-55 at their peaks), whose light curves are linear but at the
#: peak over a crossing (the detectors fitted see the source within 0.5 s of its centre): the
#: truth is the light curve at the crossing's centre, to 0.25 s / t_rise = 0.4 % at a peak
#: (t_rise, t_decay >= 60 s) and exactly elsewhere
FLARES = [{"at_detector": "w16_f090_p100A", "at_time": 300.0, "t_peak": 300.0,
           "s_peak_mjy": 1000.0, "t_rise": 250.0},
          {"at_detector": "w16_f090_p300B", "at_time": 200.0, "t_peak": 250.0,
           "s_peak_mjy": 700.0, "t_rise": 100.0, "t_decay": 300.0},
          {"at_detector": "w16_f090_p400A", "at_time": 420.0, "t_peak": 400.0,
           "s_peak_mjy": 1500.0, "t_rise": 60.0, "t_decay": 150.0}]
STEADY = [{"at_detector": "w16_f090_p200A", "at_time": 150.0, "flux_mjy": 400.0},
          {"at_detector": "w16_f090_p050B", "at_time": 500.0, "flux_mjy": 600.0},
          {"at_detector": "w16_f090_p250A", "at_time": 75.0, "flux_mjy": 300.0}]
#: nine 5 Jy sources (S/N 200 a crossing) on detectors all over the wafer
BRIGHT = [{"at_detector": f"w16_f090_p{k:03d}A", "at_time": 20.0 + 20 * i, "flux_mjy": 5000.0}
          for i, k in enumerate((20, 60, 100, 150, 200, 250, 300, 350, 400))]
#: per-crossing pull bound: 25-50 Gaussian pulls all stay within 4.5 with 99.97 % chance.
#: Measured: largest 2.0 (seed 4); over seeds 3-6 one of 4.3 in 96 crossings (seed 3, a 600 mJy
#: source read as 705 +- 27: the fit with a free position finds the same flux there), every
#: other below 2.1
MAX_PULL = 4.5


def template_factor(speed_ratio):
    """Fitted over true flux for a crossing ``speed_ratio`` times faster than the template's
    speed (white-noise limit; the 1.23 Hz high-pass is far below a 0.016 s crossing's band).

    With the template's width as unit and s = 1 / ``speed_ratio`` the crossing's: the filter
    (normalized to give 1 for a crossing of width 1) turns a unit-peak Gaussian of width s
    into one of peak sqrt(2) s / w1 and width w1 = sqrt(s^2 + 1), where the fit's model, the
    response to the template, has peak 1 and width w2 = sqrt(2). The least-squares amplitude
    of the model on it is that peak times the overlap of unit-peak Gaussians of widths w1 and
    w2 over the model's norm, sqrt(2) w1 / sqrt(w1^2 + w2^2)."""
    s = 1.0 / np.asarray(speed_ratio, float)
    w1, w2 = np.hypot(s, 1.0), np.sqrt(2.0)
    return np.sqrt(2.0) * s / w1 * np.sqrt(2.0) * w1 / np.hypot(w1, w2)


def sidelobe_leak(data, shift_s, sigma_t):
    """Forced-fit flux at a position ``shift_s`` seconds along the scan from a source, over the
    source's: the filter's response r correlated with itself, sum r(t) r(t - shift) / sum r^2,
    over the samples the fit uses (as far along the scan as the response exceeds 0.02, plus 3
    beam sigmas; the offset C fitted beside the flux changes it by < 0.5 %: r has zero mean)."""
    lags, response = data.lags, data.response[0]
    fine = np.linspace(lags[0], lags[-1], 20001)
    r = np.interp(fine, lags, response, left=0.0, right=0.0)
    shifted = np.interp(fine - shift_s, lags, response, left=0.0, right=0.0)
    support = np.max(np.abs(lags[np.abs(response) > 0.02])) + 3 * sigma_t
    used = np.abs(fine) <= support
    return float(np.sum(r[used] * shifted[used]) / np.sum(r[used] ** 2))


def drift_speed(data, ra, dec, times):
    """Speed (rad/s) of (ra, dec) across the focal plane at ``times``."""
    v = drift_velocity(data.timestamps, data.bore_q, np.full(len(times), ra),
                       np.full(len(times), dec), times)
    return np.hypot(v[:, 0], v[:, 1])


def offset_position(data, ra, dec, t_center, along, across):
    """The sky position ``along`` and ``across`` (radians) the scan from (ra, dec), in the focal
    plane at ``t_center``."""
    k = int(np.searchsorted(data.timestamps, t_center))
    v = drift_velocity(data.timestamps, data.bore_q, [ra], [dec], [t_center])[0]
    ux, uy = v / np.hypot(*v)
    xi, eta = pointing.source_in_focal_plane(data.bore_q[k:k + 1], ra, dec)
    ra2, dec2 = pointing.radec_of_samples(data.bore_q, [xi[0] + along * ux - across * uy],
                                          [eta[0] + along * uy + across * ux], [0], [k])
    return float(ra2[0]), float(dec2[0])


class Group:
    """A filtered simulated group and the forced photometry of any position in it."""

    def __init__(self, sim):
        self.sim = sim
        aman = load_group(sim)
        run_steps(aman, FILTER)
        find = FindConfig()
        self.data = FitInputs.from_aman(aman, speed_tolerance=find.speed_tolerance)
        # the template's width, and the sky speed transient_filter made it for
        self.sigma_t = float(np.median(np.asarray(aman.transient_filter.sigma_t)))
        self.template_speed = float(np.median(self.data.beam_sigma)) / self.sigma_t
        self.scan, _ = group_scans(aman.timestamps, aman.boresight.az, aman.boresight.el, find)
        self.dets = np.arange(aman.dets.count)
        self.reach = 3 * float(np.median(self.data.beam_sigma))
        # the error scales as transient_fit measures them, clear of every source's crossings,
        # on 2000 null positions: with the default 200, its robust spread is known to 8 %
        # (measured 0.87-1.15 over seeds 3-6), which every pull would inherit
        sources = Sources.join(Sources.at(self.crossings(ra, dec), ra, dec)
                               for ra, dec, _ in self.truth())
        self.scale = measure_error_scales(self.data, self.dets, sources, FitConfig(n_null=2000))

    def truth(self):
        """(ra, dec, light curve) of every simulated source."""
        out = [(f["ra"], f["dec"],
                lambda t, f=f: flare_flux(t, f["t_peak"], f["s_peak"], f["t_rise"], f["t_decay"],
                                          f["eta_rise"], f["eta_decay"]))
               for f in self.sim.flares]
        out += [(p["ra"], p["dec"], lambda t, p=p: np.full(np.shape(t), float(p["flux"])))
                for p in self.sim.point_sources]
        return out

    def factor(self, ra, dec, times):
        """:func:`template_factor` of (ra, dec)'s crossings at ``times``."""
        return template_factor(drift_speed(self.data, ra, dec, times) / self.template_speed)

    def crossings(self, ra, dec):
        t = self.data.timestamps
        return group_crossings(self.data, self.scan, ra, dec, t[0], t[-1], self.dets,
                               self.reach)[0]

    def measure(self, ra, dec):
        """Forced photometry at (ra, dec) at every crossing: the fitted crossings'
        ``t_center`` beside measure_crossings' columns."""
        times = self.crossings(ra, dec)
        res = measure_crossings(self.data, ra, dec, times, self.dets, self.scale, FitConfig(),
                                PhotometryConfig())
        res["t_center"] = times[res.pop("keep")]
        return res


@pytest.fixture(scope="module")
def sources(module_tmp):
    """600 s of w16 at f090 (white noise; no atmosphere, no CMB): three flares and three
    steady sources at 0.3-1.5 Jy, at least 40' apart."""
    group = Group(run_sim(module_tmp("forced"), seed=4,
                          observation={"duration": 600.0}, instrument=W16,
                          atmosphere={"enabled": False}, cmb={"enabled": False},
                          point_sources={"list": STEADY}, flares={"list": FLARES}))
    c = SkyCoord([s[0] for s in group.truth()] * u.rad, [s[1] for s in group.truth()] * u.rad)
    sep = c[:, None].separation(c[None, :]).to_value(u.arcmin)
    assert np.min(sep + np.diag(np.full(len(c), np.inf))) > 40   # beyond each other's sidelobes
    return group


@pytest.fixture(scope="module")
def bright(module_tmp):
    """200 s of w16 at f090 (white noise): nine 5 Jy steady sources."""
    return Group(run_sim(module_tmp("forced_bright"), seed=4,
                         observation={"duration": 200.0}, instrument=W16,
                         atmosphere={"enabled": False}, cmb={"enabled": False},
                         point_sources={"list": BRIGHT}))


def chi2_bounds(n):
    """Two-sided 99.7 % interval of a chi-squared with ``n`` degrees of freedom."""
    return stats.chi2.ppf(0.0015, n), stats.chi2.ppf(0.9985, n)


def check_pulls(pulls, what):
    """Every pull within MAX_PULL, their sum of squares within the chi-squared's 99.7 %
    interval (the fit errors describe the scatter) and their mean within 3 / sqrt(n)."""
    pulls = np.asarray(pulls)
    n = len(pulls)
    lo, hi = chi2_bounds(n)
    assert np.all(np.abs(pulls) < MAX_PULL), f"{what}: pulls {np.round(pulls, 2)}"
    assert lo < np.sum(pulls**2) < hi, f"{what}: chi2 {np.sum(pulls**2):.1f} for {n}"
    assert abs(np.mean(pulls)) < 3 / np.sqrt(n), f"{what}: mean pull {np.mean(pulls):+.2f}"


def test_forced_flux_at_the_true_position_follows_the_simulated_light_curve(sources):
    """At every crossing of each source (flares rising, at their peak, decaying and off;
    steady sources), the forced flux against the simulator's light curve at the crossing's
    centre times :func:`template_factor`: pulls from the fit errors. Measured: 24 crossings
    fitted (3 with the flares off), chi2 19.0 (99.7 % interval 8.5-49.8), mean pull -0.24,
    largest 2.0; over seeds 3-6, chi2 19-42. The flux scale is known to 1 % here: a position
    40" off fails (pulls to -5), one 20" off (a 1.5-3 % loss) does not; the bright sources'
    test below resolves that."""
    pulls, weights, ratios, off = [], [], [], 0
    for ra, dec, light_curve in sources.truth():
        res = sources.measure(ra, dec)
        t = res["t_center"]
        expected = light_curve(t) * sources.factor(ra, dec, t)
        pulls += list((res["flux"] - expected) / res["flux_err"])
        on = expected > 0
        off += int(np.sum(~on))
        weights += list((expected[on] / res["flux_err"][on]) ** 2)
        ratios += list(res["flux"][on] / expected[on])
    assert len(pulls) >= 20 and off >= 2                  # the flares were off at some
    check_pulls(pulls, "true position")
    # the flux scale: the inverse-variance mean of flux / expected within 3 of its errors
    # (measured 0.989 +- 0.010; over seeds 3-6, 0.987-1.013)
    weights, ratios = np.asarray(weights), np.asarray(ratios)
    mean, err = np.sum(weights * ratios) / np.sum(weights), 1 / np.sqrt(np.sum(weights))
    assert abs(mean - 1) < 3 * err, f"flux scale {mean:.4f} +- {err:.4f}"


def test_forced_flux_ten_arcmin_across_the_scan_is_zero(sources):
    """10' across the scan from each source (its beam there: exp(-0.5 (10 / 0.93)^2) = 1e-25),
    at every crossing of that position: fluxes consistent with zero, from the fit errors.
    Measured: 46 crossings, chi2 39.3 (99.7 % interval 22.6-79.7), mean -0.23, largest 1.9;
    over seeds 3-6, chi2 39-58, largest 3.4."""
    data = sources.data
    pulls = []
    for ra, dec, _ in sources.truth():
        t0 = sources.crossings(ra, dec)
        for side in (1, -1):
            pos = offset_position(data, ra, dec, t0[len(t0) // 2], 0.0, side * 10 * ARCMIN)
            res = sources.measure(*pos)
            pulls += list(res["flux"] / res["flux_err"])
    assert len(pulls) >= 20
    check_pulls(pulls, "10' across the scan")


def test_bright_sources_are_low_by_the_template_factor(bright):
    """Nine 5 Jy sources at S/N 200 a crossing: the fitted flux over the true is the
    :func:`template_factor` of each crossing's speed (1.5-2.3 % low): 16 crossings, measured
    0.9802, predicted 0.9816, difference -0.0013 +- 0.0016; within 3 standard errors of the
    mean of the differences (their scatter, 0.77 % a crossing, is wider than the fit errors',
    0.5 %: the fit's own model errors). A change to the template's speed (one per wafer, or
    per detector) shows here: update the factor."""
    measured, predicted = [], []
    for ra, dec, light_curve in bright.truth():
        res = bright.measure(ra, dec)
        t = res["t_center"]
        measured += list(res["flux"] / light_curve(t))
        predicted += list(bright.factor(ra, dec, t))
    measured, predicted = np.asarray(measured), np.asarray(predicted)
    assert len(measured) >= 12
    assert np.all((predicted > 0.97) & (predicted < 0.99))
    diff = measured - predicted
    assert abs(diff.mean()) < 3 * diff.std(ddof=1) / np.sqrt(len(diff)), \
        f"fitted / true {measured.mean():.4f}, predicted {predicted.mean():.4f}"


def test_a_source_ten_arcmin_along_the_scan_leaks_its_sidelobe(bright):
    """10' along the scan (before and after) from each 5 Jy source, at the source's crossings:
    the forced flux is the source's times :func:`sidelobe_leak` (the filter's response
    correlated with itself 10' apart, -16 %) times its :func:`template_factor`; within 3
    standard errors of the ratios' mean plus 0.005 for what the 1-D correlation leaves out
    (the fitted offset, the beam across the scan). Measured: 32 crossings, -0.1626 against
    -0.1620 predicted, difference -0.0006 +- 0.0012."""
    data = bright.data
    measured, predicted = [], []
    for ra, dec, light_curve in bright.truth():
        t0 = bright.crossings(ra, dec)
        for side in (1, -1):
            pos = offset_position(data, ra, dec, t0[0], side * 10 * ARCMIN, 0.0)
            res = bright.measure(*pos)          # crossed with the source: steady, 0.17 s apart
            t = res["t_center"]
            leak = [sidelobe_leak(data, 10 * ARCMIN / v, bright.sigma_t)
                    for v in drift_speed(data, ra, dec, t)]
            measured += list(res["flux"] / light_curve(t))
            predicted += list(np.asarray(leak) * bright.factor(ra, dec, t))
    measured, predicted = np.asarray(measured), np.asarray(predicted)
    assert len(measured) >= 20
    assert np.all(predicted < -0.1)
    diff = measured - predicted
    assert abs(diff.mean()) < 3 * diff.std(ddof=1) / np.sqrt(len(diff)) + 0.005, \
        f"leak {measured.mean():.4f}, predicted {predicted.mean():.4f}"
