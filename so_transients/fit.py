"""Beam-model fit of a candidate (Clancy et al. 2025, section 4.2, eq. 3).

All samples of the group within ``window`` seconds of the candidate's median time (and within
``radius`` of its position) are fitted with

    A(theta) = A0 B(theta - theta_src) + C

on the amplitude timestream, by a bounded Levenberg-Marquardt fit (:func:`levenberg_marquardt`:
four parameters, so each step solves 4 x 4 normal equations instead of decomposing the
Jacobian of every sample). Samples farther along the scan
than the filter's response reaches (plus the allowed position shift) carry no beam signal and
are left out. The fit works in focal-plane
coordinates: over one second the sky position ``theta_src`` traces a known track across the
focal plane (one quaternion per sample), and a shift of the source on the sky is a constant
shift ``(dxi, deta)`` of that track, so every sample's offset from the source is exact without
computing RA/Dec per sample. ``B`` is the Gaussian beam as it appears after the matched filter:
across the scan the beam itself, ``exp(-d^2 / 2 sigma^2)``; along the scan the filter's
response to a crossing (``response`` over ``lags``), at the time offset ``d_along / v``.

Errors. The fit covariance treats samples as independent, which they are not: filtered samples
are correlated over the response width (``inflation``, see
:func:`so_transients.matched_filter.fit_error_inflation`) and neighbouring detectors share
residual atmosphere. So errors are *measured*: :func:`null_scatter` fits the amplitude at
random positions away from candidates, and the robust spread of ``A / sigma_A`` there
(``error_scale``) multiplies every error.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import spectral_ops
from .matched_filter import mad_std

FIT_FIELDS = ("flux", "flux_err", "dxi", "deta", "dxi_err", "deta_err", "offset", "offset_err",
              "snr_fit", "chi2_red", "n_fit_samples", "n_fit_dets", "fit_ok")


@dataclass
class FitConfig:
    window: float = 0.5          # s, half-width of the time window around the median time
    radius: float = np.radians(1.0)
    min_snr: float = 5.0         # keep A0 / sigma_A >= min_snr
    cross_scan_sigma: float = 6.0  # detectors passing within this many beam sigmas are fitted
    #                               (the 3 sigma position range plus 3 sigma of beam)
    n_null: int = 200            # random positions used to measure the error scale


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


def _shape(track, along0, across0, dxi, deta):
    ux, uy = track.along
    along = along0 - (dxi * ux + deta * uy)
    across = across0 - (-dxi * uy + deta * ux)
    tau = along / track.speed
    resp = np.interp(tau, track.lags, track.response, left=0.0, right=0.0)
    gauss = np.exp(-0.5 * (across / track.sigma) ** 2)
    return resp * gauss, tau, across, gauss


def _uniform_step(lags):
    """The spacing of ``lags`` if they are uniform (and at least two), else None."""
    if len(lags) < 2:
        return None
    step = (lags[-1] - lags[0]) / (len(lags) - 1)
    return step if step > 0 and np.allclose(np.diff(lags), step, rtol=1e-6, atol=0) else None


class _BeamModel:
    """Model and Jacobian of ``a0 B + c`` at fixed samples, one compiled pass each
    (:func:`so_transients.spectral_ops.beam_terms`) when the response lags are uniform."""

    def __init__(self, track, along0, across0):
        self.track, self.along0, self.across0 = track, along0, across0
        self.slope = np.gradient(track.response, track.lags) if len(track.lags) > 1 \
            else np.zeros_like(track.response)
        self.step = _uniform_step(np.asarray(track.lags))
        n = len(along0)
        self.shape, self.d_resp, self.d_gauss = np.empty(n), np.empty(n), np.empty(n)

    def _terms(self, dxi, deta, jac):
        t = self.track
        ux, uy = t.along
        if self.step is None:
            shape, tau, across, gauss = _shape(t, self.along0, self.across0, dxi, deta)
            if not jac:
                return shape, None, None
            d_resp = np.interp(tau, t.lags, self.slope, left=0.0, right=0.0) / t.speed * gauss
            return shape, d_resp, shape * across / t.sigma**2
        empty = np.empty(0)
        spectral_ops.beam_terms(self.along0, self.across0, dxi * ux + deta * uy,
                                -dxi * uy + deta * ux, 1.0 / t.speed, float(t.lags[0]),
                                1.0 / self.step, np.asarray(t.response, float), self.slope,
                                1.0 / t.sigma**2, self.shape,
                                self.d_resp if jac else empty, self.d_gauss if jac else empty)
        return self.shape, (self.d_resp if jac else None), (self.d_gauss if jac else None)

    def model(self, _, a0, dxi, deta, c):
        return a0 * self._terms(dxi, deta, False)[0] + c

    def jacobian(self, _, a0, dxi, deta, c):
        ux, uy = self.track.along
        shape, d_resp, d_gauss = self._terms(dxi, deta, True)
        # d along / d(dxi, deta) = -(ux, uy); d across / d(dxi, deta) = (uy, -ux)
        d_dxi = a0 * (-ux * d_resp - uy * d_gauss)
        d_deta = a0 * (-uy * d_resp + ux * d_gauss)
        return np.stack([shape, d_dxi, d_deta, np.ones_like(shape)], axis=1)


def linear_amplitude(shape, amp, weight):
    """Weighted least-squares amplitude of ``shape`` in ``amp`` and its naive error."""
    sw = np.sum(weight * shape**2)
    if sw <= 0:
        return np.nan, np.nan
    return float(np.sum(weight * shape * amp) / sw), float(1.0 / np.sqrt(sw))


def fit_candidate(track: Track, det_xi, det_eta, amp, sigma_amp, inflation=1.0, error_scale=1.0):
    """Fit ``A0 B + C`` to the window's amplitude samples ``amp`` (ndet, nt).

    ``sigma_amp``: (ndet,) noise of each detector's amplitude timestream; samples with
    ``amp == 0`` (made invalid by the filter) are ignored. Returns a dict of
    :data:`FIT_FIELDS`; ``dxi``, ``deta`` are the source's focal-plane shift from the track.
    """
    out = dict.fromkeys(FIT_FIELDS, np.nan)
    ok = (amp != 0) & (sigma_amp[:, None] > 0)
    out.update(n_fit_samples=int(ok.sum()), n_fit_dets=int(ok.any(axis=1).sum()), fit_ok=False)
    if ok.sum() < 8:
        return out
    along_all, _ = _offsets(track, det_xi, det_eta)
    support = track.speed * np.max(np.abs(track.lags[np.abs(track.response) > 0.02]), initial=0.0)
    ok &= np.abs(along_all) <= support + 3 * track.sigma   # beyond, samples only constrain C
    out.update(n_fit_samples=int(ok.sum()), n_fit_dets=int(ok.any(axis=1).sum()))
    if ok.sum() < 8:
        return out
    along0, across0 = (v[ok] for v in _offsets(track, det_xi, det_eta))
    y = amp[ok].astype(float)
    s = np.broadcast_to(sigma_amp[:, None], amp.shape)[ok]
    beam = _BeamModel(track, along0, across0)
    model, jacobian = beam.model, beam.jacobian

    a_start, _ = linear_amplitude(model(None, 1.0, 0.0, 0.0, 0.0), y, s**-2)
    reach = 3 * track.sigma
    popt, pcov = levenberg_marquardt(
        model, jacobian, y, s, np.array([max(a_start, 1e-3), 0.0, 0.0, 0.0]),
        lower=np.array([0.0, -reach, -reach, -np.inf]), upper=np.array([np.inf, reach, reach, np.inf]))
    if popt is None:
        return out
    errors = np.sqrt(np.diag(pcov)) * inflation * error_scale
    resid = (y - model(None, *popt)) / s
    out.update(flux=popt[0], flux_err=errors[0], dxi=popt[1], deta=popt[2], dxi_err=errors[1],
               deta_err=errors[2], offset=popt[3], offset_err=errors[3],
               snr_fit=popt[0] / errors[0] if errors[0] > 0 else np.nan,
               chi2_red=float(np.sum(resid**2) / max(len(y) - 4, 1)),
               fit_ok=bool(np.all(np.isfinite(errors))))
    return out


def levenberg_marquardt(model, jacobian, y, sigma, p0, lower, upper, max_iter=50,
                        tol_chi2=1e-3):
    """Weighted least squares of ``model(None, *p)`` to ``y`` with parameters kept in
    ``[lower, upper]`` (clipped after each step). Stops when a step lowers chi^2 by less than
    ``tol_chi2`` (absolute: a change of 1 moves a parameter by one sigma). Returns
    ``(p, covariance)`` with the covariance ``(J^T W J)^-1`` at the solution, or
    ``(None, None)`` if it is singular."""
    w = sigma**-2
    p = np.clip(np.asarray(p0, float), lower, upper)
    resid = y - model(None, *p)
    chi2 = np.sum(w * resid**2)
    damping = 1e-3
    for _ in range(max_iter):
        jac = jacobian(None, *p)
        alpha = jac.T @ (jac * w[:, None])
        beta = jac.T @ (w * resid)
        improved = converged = False
        while damping < 1e10:
            try:
                step = np.linalg.solve(alpha + damping * np.diag(np.diag(alpha)), beta)
            except np.linalg.LinAlgError:
                damping *= 10
                continue
            trial = np.clip(p + step, lower, upper)
            resid_trial = y - model(None, *trial)
            chi2_trial = np.sum(w * resid_trial**2)
            if chi2_trial <= chi2:
                improved, converged = True, chi2 - chi2_trial < tol_chi2
                p, resid, chi2, damping = trial, resid_trial, chi2_trial, max(damping / 10, 1e-12)
                break
            damping *= 10
        if not improved or converged:
            break
    jac = jacobian(None, *p)
    try:
        cov = np.linalg.inv(jac.T @ (jac * w[:, None]))
    except np.linalg.LinAlgError:
        return None, None
    return p, cov


def null_scatter(tracks, det_xi, det_eta, amps, sigma_amp, inflation=1.0):
    """Robust spread of ``A / sigma_A`` for amplitude fits at fixed (null) positions.

    ``tracks`` and ``amps`` are windows centred on random positions away from any candidate;
    the result is the factor by which the naive, inflated errors must grow to describe the
    actual noise (1 for independent detectors).
    """
    ratios = []
    for track, amp in zip(tracks, amps):
        shape = beam_shape(track, det_xi, det_eta)
        ok = (amp != 0) & (sigma_amp[:, None] > 0)
        a, err = linear_amplitude(shape[ok], amp[ok], (sigma_amp[:, None] ** -2 * ok)[ok])
        if np.isfinite(a):
            ratios.append(a / (err * inflation))
    if len(ratios) < 10:
        return 1.0
    return float(mad_std(ratios))
