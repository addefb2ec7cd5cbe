"""Beam-model fit of a candidate (Clancy et al. 2025, section 4.2, eq. 3).

All samples of the group within ``window`` seconds of the candidate's median time (and within
``radius`` of its position) are fitted with

    A(theta) = A0 B(theta - theta_src) + C

on the amplitude timestream, by a bounded Levenberg-Marquardt fit (:func:`levenberg_marquardt`:
four parameters, so each trial is one compiled pass over the samples that returns chi^2 and
the 4 x 4 normal equations, without forming the Jacobian). Samples farther along the scan
than the filter's response reaches (plus the allowed position shift) carry no beam signal and
are left out. The fit works in focal-plane
coordinates: over one second the sky position ``theta_src`` traces a known track across the
focal plane (one quaternion per sample), and a shift of the source on the sky is a constant
shift ``(dxi, deta)`` of that track, so every sample's offset from the source is exact without
computing RA/Dec per sample. ``B`` is the Gaussian beam as it appears after the matched filter:
across the scan the beam itself, ``exp(-d^2 / 2 sigma^2)``; along the scan the filter's
response to a crossing (``response`` over ``lags``, interpolated smoothly by
:func:`response_spline`), at the time offset ``d_along / v``.

Errors. The fit covariance treats samples as independent, which they are not: filtered samples
are correlated over the response width (``inflation``, see
:func:`so_transients.detect.matched_filter.fit_error_inflation`) and neighbouring detectors share
residual atmosphere. So errors are *measured*: the robust spread of ``A / sigma_A`` of
amplitude fits at random positions away from sources (:func:`null_ratio`), in each scan
direction, multiplies every error (``error_scale``: :mod:`so_transients.detect.error_scale`).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.interpolate import CubicHermiteSpline

from so_transients.common import pointing
from so_transients.detect import spectral_ops
from so_transients.common.angles import ARCSEC, DEG
from so_transients.detect.find import SCAN_FIELD
from so_transients.common.scan_geometry import constant_velocity, scan_direction
from so_transients.common.step_config import ConfigError, non_negative, positive, share, setting

#: The scan-speed tolerance ``transient_find`` stores in ``aman.transient_candidates``.
SPEED_TOLERANCE = "speed_tolerance"

FIT_FIELDS = ("flux", "flux_err", "dxi", "deta", "dxi_err", "deta_err", "offset", "offset_err",
              "snr_fit", "chi2_red", "n_fit_samples", "n_fit_dets", "fit_ok")


@dataclass
class FitConfig:
    window: float = setting(0.5, "s", "half-width of the time window around the median time")
    radius_deg: float = setting(1.0, "deg", "samples within this distance of the candidate are fitted")
    min_snr: float = setting(5.0, "S/N", "keep A0 / sigma_A >= min_snr")
    cross_scan_sigma: float = setting(
        6.0, "beam sigma",
        "detectors passing within this many beam sigmas are fitted (the 3 sigma position range plus 3 sigma "
        "of beam)")
    n_null: int = setting(200, "", "random positions measuring the error scale, in each scan direction")
    local_window: float | None = setting(
        None, "s",
        "a significant fit's error scale is also measured within this of it, and the larger of the two is "
        "used (null: the group's only; not with a fixed error_scale)")
    n_null_local: int = setting(400, "", "random positions of that local measurement")
    seed: int = setting(0, "", "seed of the random null positions")
    error_scale: float | list | None = setting(
        None, "",
        "fixed error scale: one for both scan directions, or [increasing azimuth, decreasing azimuth] "
        "(null: measured on the group)")
    max_motion_arcmin_per_min: float = setting(
        5.0, "arcmin / min",
        "detections this far apart per time are linked")
    min_motion_arcmin_per_min: float = setting(
        0.1, "arcmin / min",
        "a linked set moving faster is a moving source")
    motion_floor_arcsec: float = setting(10.0, "arcsec", "position error floor for the motion test")
    max_peak_ratio: float | None = setting(None, "", "not detected: snr_max > this x snr_fit (null: off)")
    max_split_sigma: float | None = setting(
        5.0, "",
        "not detected: the fits of two halves of the detectors disagree by more than this many errors "
        "(split_sigma; null: not checked)")
    split_floor_arcsec: float = setting(10.0, "arcsec", "position error floor of that comparison")
    split_floor_flux: float = setting(0.1, "", "flux error floor of that comparison, as a share of the flux")
    score_model: str | None = setting(None, "", "real-or-artefact model: a file, or \"shipped\"")
    min_real_score: float | None = setting(None, "", "not detected: real_score below this (null: off)")

    def __post_init__(self):
        positive("transient_fit", window=self.window, radius_deg=self.radius_deg,
                 min_snr=self.min_snr, cross_scan_sigma=self.cross_scan_sigma,
                 n_null=self.n_null,
                 local_window=self.local_window, n_null_local=self.n_null_local,
                 max_motion_arcmin_per_min=self.max_motion_arcmin_per_min,
                 min_motion_arcmin_per_min=self.min_motion_arcmin_per_min,
                 motion_floor_arcsec=self.motion_floor_arcsec,
                 max_peak_ratio=self.max_peak_ratio, max_split_sigma=self.max_split_sigma,
                 split_floor_arcsec=self.split_floor_arcsec,
                 split_floor_flux=self.split_floor_flux)
        non_negative("transient_fit", seed=self.seed)
        if self.error_scale is not None:
            values = self.error_scale if isinstance(self.error_scale, (list, tuple)) \
                else [self.error_scale]
            if len(values) not in (1, 2) or not all(
                    isinstance(v, (int, float)) and v > 0 for v in values):
                raise ConfigError("transient_fit: error_scale must be a positive number or two "
                                  f"([increasing azimuth, decreasing azimuth]), got "
                                  f"{self.error_scale}")
        share("transient_fit", min_real_score=self.min_real_score)
        if self.min_real_score is not None and self.score_model is None:
            raise ConfigError("transient_fit: min_real_score needs a score_model (a model "
                              "file, or 'shipped')")

    @property
    def radius(self):
        return self.radius_deg * DEG


@dataclass
class FitInputs:
    """What the fit reads of a group: pointing, the filter's S/N and its per-detector noise
    and response (``transient_filter``'s output)."""

    timestamps: np.ndarray
    bore_q: np.ndarray           # (nsamps, 4) celestial boresight quaternions
    xi: np.ndarray
    eta: np.ndarray
    snr: np.ndarray              # (ndet, nsamps), possibly memory-mapped
    sigma_amp: np.ndarray        # (ndet,) amplitude noise, mJy
    dead: np.ndarray             # (ndet,) bool
    beam_sigma: np.ndarray       # (ndet,) rad
    inflation: np.ndarray        # (ndet,) the filter's correlated-sample error inflation
    lags: np.ndarray             # the filter's response to a crossing at these lags (s) ...
    response: np.ndarray         # ... (ndet, nlag): each detector's band's
    scanning: np.ndarray = None  # (nsamps,) bool: at the template's scan speed (None: all)
    scan: np.ndarray = None      # (nsamps,) transient_find's scan index (sweep stacks' fit)
    direction: np.ndarray = None  # (nsamps,) +1 where the azimuth increases, -1 where it falls

    @classmethod
    def from_aman(cls, aman, speed_tolerance=None):
        """The inputs from an AxisManager that ``transient_filter`` has processed; samples
        scanning more than ``speed_tolerance`` off the nominal speed (turnarounds, where the
        filter's response to a crossing is not the template's) are not fitted. By default
        the tolerance ``transient_find`` searched with (``aman.transient_candidates``)."""
        if speed_tolerance is None:
            cands = aman.transient_candidates if "transient_candidates" in aman._fields else {}
            if SPEED_TOLERANCE not in getattr(cands, "_fields", ()):
                raise ValueError("aman.transient_candidates holds no speed_tolerance: run "
                                 "transient_find first")
            speed_tolerance = float(cands[SPEED_TOLERANCE])
        summary = aman.transient_filter
        t, az, el = aman.timestamps, aman.boresight.az, aman.boresight.el
        return cls(np.asarray(t), pointing.boresight_q(aman),
                   np.asarray(aman.focal_plane.xi), np.asarray(aman.focal_plane.eta),
                   aman.transient_snr, np.asarray(summary.sigma_amp),
                   np.asarray(summary.dead, bool), np.asarray(summary.beam_sigma),
                   np.asarray(summary.fit_inflation, float), np.asarray(summary.lag),
                   np.atleast_2d(np.asarray(summary.response)),
                   constant_velocity(t, az, el, speed_tolerance),
                   np.asarray(aman[SCAN_FIELD]) if SCAN_FIELD in aman._fields else None,
                   scan_direction(az))

    def kernel(self, dets):
        """``(response, inflation)`` of detectors ``dets`` (one band: they share them)."""
        row = int(dets[0]) if len(dets) else 0
        inflation = float(np.median(self.inflation[dets])) if len(dets) else 1.0
        return self.response[row], inflation

    def amplitude(self, dets, lo, hi):
        """Amplitude (mJy) of detectors ``dets``, samples ``lo:hi``: S/N x sigma_amp; zero
        (not fitted) where the boresight is not scanning at the template's speed."""
        sigma = np.asarray(self.sigma_amp, np.float32)[dets]
        amp = np.asarray(self.snr[dets, lo:hi]) * sigma[:, None]
        if self.scanning is not None:
            amp *= self.scanning[lo:hi]
        return amp


@dataclass
class Track:
    """A sky position's path across the focal plane during a fit window, and the beam there."""

    xi: np.ndarray              # (nt,) source position per window sample
    eta: np.ndarray
    along: np.ndarray           # unit vector of the drift in the focal plane
    speed: float                # rad/s
    sigma: float                # beam sigma, rad
    lags: np.ndarray
    response: np.ndarray


def _offsets(track: Track, det_xi, det_eta):
    """Along- and across-scan offsets (ndet, nt) of detectors from the unshifted track."""
    ox = det_xi[:, None] - track.xi[None, :]
    oy = det_eta[:, None] - track.eta[None, :]
    return (ox * track.along[0] + oy * track.along[1],
            -ox * track.along[1] + oy * track.along[0])


def beam_shape(track: Track, det_xi, det_eta, dxi=0.0, deta=0.0):
    """Beam-through-filter response, shape (ndet, nt), for a source shifted by (dxi, deta)."""
    along, across = _offsets(track, det_xi, det_eta)
    return _shape(track, along, across, dxi, deta)[0]


def response_slope(track: Track):
    """d response / d lag at each of ``track.lags``."""
    response = np.asarray(track.response, float)
    return np.gradient(response, track.lags) if len(response) > 1 else np.zeros_like(response)


def response_spline(track: Track):
    """The filter's response as a function of time offset: the cubic Hermite interpolant of
    ``track.response`` with :func:`response_slope`, NaN outside ``track.lags``. Unlike
    linear interpolation it has a continuous derivative, so chi^2 varies smoothly with the
    source position (with kinks at every lag, a fit's steps stall between them)."""
    return CubicHermiteSpline(np.asarray(track.lags, float), np.asarray(track.response, float),
                              response_slope(track), extrapolate=False)


def _shape(track, along0, across0, dxi, deta, spline=None):
    ux, uy = track.along
    along = along0 - (dxi * ux + deta * uy)
    across = across0 - (-dxi * uy + deta * ux)
    tau = along / track.speed
    spline = response_spline(track) if spline is None else spline
    resp = np.nan_to_num(spline(tau))
    gauss = np.exp(-0.5 * (across / track.sigma) ** 2)
    return resp * gauss, tau, across, gauss


def _uniform_step(lags):
    """The spacing of ``lags`` if they are uniform (and at least two), else None."""
    if len(lags) < 2:
        return None
    step = (lags[-1] - lags[0]) / (len(lags) - 1)
    return step if step > 0 and np.allclose(np.diff(lags), step, rtol=1e-6, atol=0) else None


class _BeamModel:
    """chi^2 and normal equations of ``a0 B + c`` at fixed samples ``y`` (errors ``sigma``):
    one compiled pass (:func:`so_transients.detect.spectral_ops.beam_normal_equations`) when the
    response lags are uniform, else numpy through :meth:`model` and :meth:`jacobian`."""

    def __init__(self, track, along0, across0, y, sigma):
        self.track, self.along0, self.across0 = track, along0, across0
        self.y, self.w = y, sigma**-2.0
        self.response = np.asarray(track.response, float)
        self.slope = response_slope(track)
        step = _uniform_step(np.asarray(track.lags))
        ux, uy = track.along
        self.geom = None if step is None else np.array(
            [ux, uy, 1.0 / track.speed, float(track.lags[0]), 1.0 / step, track.sigma**-2.0])

    @cached_property
    def spline(self):
        """The numpy path's response interpolant (the compiled pass interpolates itself)."""
        return response_spline(self.track)

    def model(self, p):
        a0, dxi, deta, c = p
        return a0 * _shape(self.track, self.along0, self.across0, dxi, deta, self.spline)[0] + c

    def jacobian(self, p):
        a0, dxi, deta, _ = p
        t = self.track
        ux, uy = t.along
        shape, tau, across, gauss = _shape(t, self.along0, self.across0, dxi, deta, self.spline)
        d_resp = np.nan_to_num(self.spline(tau, 1)) / t.speed * gauss
        d_gauss = shape * across / t.sigma**2
        # d along / d(dxi, deta) = -(ux, uy); d across / d(dxi, deta) = (uy, -ux)
        return np.stack([shape, a0 * (-ux * d_resp - uy * d_gauss),
                         a0 * (-uy * d_resp + ux * d_gauss), np.ones_like(shape)], axis=1)

    def normal_equations(self, p):
        """``(chi2, J^T W J, J^T W r)`` at parameters ``p = (a0, dxi, deta, c)``."""
        p = np.asarray(p, float)
        if self.geom is not None:
            alpha, beta = np.empty((4, 4)), np.empty(4)
            chi2 = spectral_ops.beam_normal_equations(self.along0, self.across0, self.y, self.w,
                                                      p, self.geom, self.response, self.slope,
                                                      alpha, beta)
            return chi2, alpha, beta
        resid = self.y - self.model(p)
        jac = self.jacobian(p)
        return (float(np.sum(self.w * resid**2)), jac.T @ (jac * self.w[:, None]),
                jac.T @ (self.w * resid))

    def amplitude(self):
        """Least-squares ``a0`` of the unshifted beam alone (no offset) and its naive error."""
        _, alpha, beta = self.normal_equations(np.zeros(4))
        if alpha[0, 0] <= 0:
            return np.nan, np.nan
        return float(beta[0] / alpha[0, 0]), float(alpha[0, 0] ** -0.5)


def _reach(track):
    """How far along the scan (rad) a sample can carry the beam: as far as the filter's
    response reaches, plus 3 beam sigmas (beyond, samples only constrain C)."""
    support = track.speed * np.max(np.abs(track.lags[np.abs(track.response) > 0.02]), initial=0.0)
    return support + 3 * track.sigma


def _beam_samples(track, det_xi, det_eta, amp, sigma_amp):
    """The window's samples that can carry the beam: valid (``amp != 0``, ``sigma_amp > 0``)
    and within :func:`_reach` along the scan. Returns a :class:`_BeamModel` on them."""
    ok = (amp != 0) & (sigma_amp[:, None] > 0)
    along, across = _offsets(track, det_xi, det_eta)
    ok &= np.abs(along) <= _reach(track)
    sigma = np.broadcast_to(sigma_amp[:, None], amp.shape)[ok]
    return _BeamModel(track, along[ok], across[ok], amp[ok].astype(float), sigma), ok


def fit_candidate(track: Track, det_xi, det_eta, amp, sigma_amp, inflation=1.0, error_scale=1.0):
    """Fit ``A0 B + C`` to the window's amplitude samples ``amp`` (ndet, nt).

    ``sigma_amp``: (ndet,) noise of each detector's amplitude timestream; samples with
    ``amp == 0`` (made invalid by the filter) are ignored. Returns a dict of
    :data:`FIT_FIELDS`; ``dxi``, ``deta`` are the source's focal-plane shift from the track.
    """
    out = dict.fromkeys(FIT_FIELDS, np.nan)
    beam, ok = _beam_samples(track, det_xi, det_eta, amp, sigma_amp)
    out.update(n_fit_samples=int(ok.sum()), n_fit_dets=int(ok.any(axis=1).sum()), fit_ok=False)
    if ok.sum() < 8:
        return out
    a_start, _ = beam.amplitude()
    reach = 3 * track.sigma
    popt, pcov, chi2 = levenberg_marquardt(
        beam.normal_equations, np.array([max(np.nan_to_num(a_start), 1e-3), 0.0, 0.0, 0.0]),
        lower=np.array([0.0, -reach, -reach, -np.inf]), upper=np.array([np.inf, reach, reach, np.inf]))
    if popt is None:
        return out
    errors = np.sqrt(np.diag(pcov)) * inflation * error_scale
    out.update(flux=popt[0], flux_err=errors[0], dxi=popt[1], deta=popt[2], dxi_err=errors[1],
               deta_err=errors[2], offset=popt[3], offset_err=errors[3],
               snr_fit=popt[0] / errors[0] if errors[0] > 0 else np.nan,
               chi2_red=float(chi2 / max(ok.sum() - 4, 1)),
               fit_ok=bool(np.all(np.isfinite(errors))))
    return out


def fit_fixed_position(track: Track, det_xi, det_eta, amp, sigma_amp, inflation=1.0,
                       error_scale=1.0):
    """Forced photometry: ``A0 B + C`` fitted with the source held at the track (the model is
    then linear in ``A0`` and ``C``: one weighted least-squares solve, no iteration). Returns
    ``flux``, ``flux_err``, ``offset``, ``offset_err`` (mJy, errors scaled as
    :func:`fit_candidate`'s), ``chi2_red``, ``n_fit_samples``, ``n_fit_dets`` and ``fit_ok``."""
    beam, ok = _beam_samples(track, det_xi, det_eta, amp, sigma_amp)
    out = dict(flux=np.nan, flux_err=np.nan, offset=np.nan, offset_err=np.nan,
               chi2_red=np.nan, n_fit_samples=int(ok.sum()),
               n_fit_dets=int(ok.any(axis=1).sum()), fit_ok=False)
    if ok.sum() < 8:
        return out
    chi2_zero, alpha, beta = beam.normal_equations(np.zeros(4))
    linear = [0, 3]                       # A0 and C; the position (1, 2) is held
    matrix = alpha[np.ix_(linear, linear)]
    try:
        cov = np.linalg.inv(matrix)
    except np.linalg.LinAlgError:
        return out
    (a0, c) = cov @ beta[linear]
    chi2 = chi2_zero - float(beta[linear] @ cov @ beta[linear])
    errors = np.sqrt(np.clip(np.diag(cov), 0, None)) * inflation * error_scale
    out.update(flux=float(a0), flux_err=float(errors[0]), offset=float(c),
               offset_err=float(errors[1]), chi2_red=float(chi2 / max(ok.sum() - 2, 1)),
               fit_ok=bool(np.all(np.isfinite(errors)) and errors[0] > 0))
    return out


def _held(p, lower, upper, beta):
    """Parameters at a bound that the chi^2 gradient pushes outwards (``beta`` is minus half
    the gradient): they stay at the bound for the next step."""
    return ((p <= lower) & (beta < 0)) | ((p >= upper) & (beta > 0))


def _solve(matrix, beta, free):
    """Solution of ``matrix x = beta`` for the ``free`` parameters, 0 for the others."""
    x = np.zeros_like(beta)
    x[free] = np.linalg.solve(matrix[np.ix_(free, free)], beta[free])
    return x


def levenberg_marquardt(normal_equations, p0, lower, upper, max_iter=50, tol_chi2=1e-3):
    """Weighted least squares with parameters kept in ``[lower, upper]``.

    ``normal_equations(p)`` returns ``(chi2, J^T W J, J^T W r)`` at ``p``. Parameters at a
    bound that the gradient pushes outwards are held there for the step (a projected step, so
    a bound does not stall the fit), others are clipped to the bounds. Stops when a step
    lowers chi^2, or an undamped (Gauss-Newton) step would, by less than ``tol_chi2``
    (absolute: a change of 1 moves a parameter by one sigma). Returns
    ``(p, covariance, chi2)`` with the covariance ``(J^T W J)^-1`` at the solution, or
    ``(None, None, None)`` if it is singular."""
    p = np.clip(np.asarray(p0, float), lower, upper)
    chi2, alpha, beta = normal_equations(p)
    damping = 1e-3
    for _ in range(max_iter):
        free = ~_held(p, lower, upper, beta)
        try:
            if not free.any() or beta @ _solve(alpha, beta, free) < tol_chi2:
                break                 # the (bounded) minimum is nearer than tol_chi2
        except np.linalg.LinAlgError:
            pass
        improved = converged = False
        while damping < 1e10:
            try:
                step = _solve(alpha + damping * np.diag(np.diag(alpha)), beta, free)
            except np.linalg.LinAlgError:
                damping *= 10
                continue
            trial = np.clip(p + step, lower, upper)
            chi2_trial, alpha_trial, beta_trial = normal_equations(trial)
            if chi2_trial <= chi2:
                improved, converged = True, chi2 - chi2_trial < tol_chi2
                p, chi2, alpha, beta = trial, chi2_trial, alpha_trial, beta_trial
                damping = max(damping / 10, 1e-12)
                break
            damping *= 10
        if not improved or converged:
            break
    try:
        cov = np.linalg.inv(alpha)
    except np.linalg.LinAlgError:
        return None, None, None
    return p, cov, chi2


def null_ratio(window, inflation=1.0) -> float:
    """``A / sigma_A`` (errors inflated by ``inflation``) of the unshifted beam's amplitude fit
    on ``window`` (``(track, det_xi, det_eta, amp, sigma_amp)``, as :func:`fit_candidate`
    takes it); NaN when no sample can carry the beam. The same sums as
    :meth:`_BeamModel.amplitude` on :func:`_beam_samples`, in one compiled pass when the
    response's lags are uniform (2000 of these measure a paper-mode group's error scale)."""
    track, det_xi, det_eta, amp, sigma_amp = window
    step = _uniform_step(np.asarray(track.lags))
    if step is None:
        beam, ok = _beam_samples(*window)
        a, err = beam.amplitude() if ok.any() else (np.nan, np.nan)
    else:
        ux, uy = track.along
        geom = np.array([ux, uy, 1.0 / track.speed, float(track.lags[0]), 1.0 / step,
                         track.sigma**-2.0])
        response = np.asarray(track.response, float)
        wyb, wbb, n = spectral_ops.beam_amplitude_sums(
            np.asarray(track.xi, float), np.asarray(track.eta, float),
            np.asarray(det_xi, float), np.asarray(det_eta, float), amp,
            np.asarray(sigma_amp, float), _reach(track), geom, response,
            response_slope(track))
        a, err = (wyb / wbb, wbb**-0.5) if n and wbb > 0 else (np.nan, np.nan)
    return a / (err * inflation) if np.isfinite(a) else np.nan


def split_sigma(track: Track, det_xi, det_eta, amp, sigma_amp, inflation=1.0, error_scale=1.0,
                floor=10 * ARCSEC, floor_flux=0.1):
    """How far apart the fits of two halves of the detectors are, in errors: the window's
    detectors sorted across the scan are dealt alternately into two halves (each spans the
    source's whole cross-scan profile), each half is fitted (:func:`fit_candidate`), and
    the larger of the position difference over its combined error (with ``floor``, rad, in
    quadrature) and the flux difference over its combined error (with ``floor_flux`` of
    the mean flux) is returned; NaN when a half cannot be fitted.

    A source the data support gives two halves that agree; a fit pulled by a few detectors
    whose data or weights are wrong (a dead channel weighted as a live one, a detector whose
    pointing is off) gives halves that do not."""
    mid = len(track.xi) // 2
    across = _offsets(track, det_xi, det_eta)[1][:, mid]
    order = np.argsort(across, kind="stable")
    fits = [fit_candidate(track, det_xi[h], det_eta[h], amp[h], sigma_amp[h], inflation,
                          error_scale) for h in (order[0::2], order[1::2])]
    if not all(f["fit_ok"] for f in fits):
        return np.nan
    a, b = fits
    position = np.hypot(a["dxi"] - b["dxi"], a["deta"] - b["deta"]) / np.sqrt(
        a["dxi_err"] ** 2 + b["dxi_err"] ** 2 + a["deta_err"] ** 2 + b["deta_err"] ** 2
        + floor ** 2)
    flux = abs(a["flux"] - b["flux"]) / np.sqrt(
        a["flux_err"] ** 2 + b["flux_err"] ** 2 + (floor_flux * 0.5 * (a["flux"] + b["flux"])) ** 2)
    return float(max(position, flux))


# ----------------------------------------------------------------------------- a group's fits

def source_track(data: FitInputs, ra, dec, lo, hi, dets):
    """``(q, track)``: the boresight quaternions of samples ``lo:hi`` and the sky position's
    path across the focal plane then, with the filter response of detectors ``dets``' band
    (beam sigma still unset)."""
    t = data.timestamps
    q = data.bore_q[lo:hi]
    xi, eta = pointing.source_in_focal_plane(q, ra, dec)
    # the drift at the window's centre (the window may reach into a turnaround)
    mid, k = (hi - lo) // 2, max(1, (hi - lo) // 20)
    a, b = max(mid - k, 0), min(mid + k, hi - lo - 1)
    velocity = np.array([xi[b] - xi[a], eta[b] - eta[a]]) / (t[lo + b] - t[lo + a])
    speed = float(np.hypot(*velocity))
    return q, Track(xi, eta, velocity / speed, speed, 0.0, data.lags, data.kernel(dets)[0])


def fit_window(data: FitInputs, ra, dec, lo, hi, dets, cfg: FitConfig):
    """The source's track over samples ``lo:hi`` and the detectors of ``dets`` that pass
    within ``radius`` and ``cross_scan_sigma`` beam sigmas of it: ``(q, track, dets)``."""
    q, track = source_track(data, ra, dec, lo, hi, dets)
    mid = (hi - lo) // 2
    xi, eta = data.xi[dets], data.eta[dets]
    near = pointing.angular_distance_xieta(xi, eta, track.xi[mid], track.eta[mid]) <= cfg.radius
    track.sigma = float(np.median(data.beam_sigma[dets])) if len(dets) else 1.0
    across = -(xi - track.xi[mid]) * track.along[1] + (eta - track.eta[mid]) * track.along[0]
    return q, track, dets[near & (np.abs(across) <= cfg.cross_scan_sigma * track.sigma)]


def window_arrays(data: FitInputs, track, dets, lo, hi):
    """``(track, det_xi, det_eta, amp, sigma_amp)`` of detectors ``dets``, samples ``lo:hi``,
    as :func:`fit_candidate` takes them."""
    return track, data.xi[dets], data.eta[dets], data.amplitude(dets, lo, hi), data.sigma_amp[dets]


def to_sky(q, xi0, eta0, res):
    """RA/Dec and errors of the fitted focal-plane position at the window's centre."""
    step = 1e-5
    xs = xi0 + res["dxi"] + np.array([0.0, step, 0.0])
    es = eta0 + res["deta"] + np.array([0.0, 0.0, step])
    ra, dec = pointing.radec_of_samples(q, xs, es, [0, 1, 2], [0, 0, 0])
    dra = np.angle(np.exp(1j * (ra[1:] - ra[0]))) * np.cos(dec[0]) / step
    ddec = (dec[1:] - dec[0]) / step
    cov = np.diag([res["dxi_err"] ** 2, res["deta_err"] ** 2])
    jac = np.array([dra, ddec])
    cov_sky = jac @ cov @ jac.T
    return dict(ra=float(ra[0]), dec=float(dec[0]), ra_err=float(np.sqrt(cov_sky[0, 0])),
                dec_err=float(np.sqrt(cov_sky[1, 1])))


def fit_at(data: FitInputs, ra, dec, t_center, band_dets, error_scale, cfg: FitConfig):
    """The beam fit of a candidate at (ra, dec) around ``t_center`` on the live detectors of
    ``band_dets``: :func:`fit_candidate`'s dict plus RA/Dec and their errors ({} when the
    window is too short)."""
    lo, hi = np.searchsorted(data.timestamps, [t_center - cfg.window, t_center + cfg.window])
    if hi - lo < 4:        # at the very end of the data: nothing to fit
        return dict(n_fit_samples=0, n_fit_dets=0, fit_ok=False, error_scale=error_scale)
    live = band_dets[~data.dead[band_dets]]
    q, track, dets = fit_window(data, ra, dec, lo, hi, live, cfg)
    arrays, inflation = window_arrays(data, track, dets, lo, hi), data.kernel(live)[1]
    res = fit_candidate(*arrays, inflation, error_scale)
    res["error_scale"] = error_scale
    if res["fit_ok"] and cfg.max_split_sigma is not None and res["snr_fit"] >= cfg.min_snr:
        res["split_sigma"] = split_sigma(*arrays, inflation, error_scale,
                                         cfg.split_floor_arcsec * ARCSEC, cfg.split_floor_flux)
    if res["fit_ok"]:
        mid = (hi - lo) // 2
        res.update(to_sky(q[mid:mid + 1], track.xi[mid], track.eta[mid], res))
    return res
