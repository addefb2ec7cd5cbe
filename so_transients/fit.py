"""Beam-model fit of a candidate (Clancy et al. 2025, section 4.2, eq. 3).

All samples of the group within ``window`` seconds of the candidate's median time (and within
``radius`` of its position) are fitted with

    A(theta) = A0 B(theta - theta_src) + C

on the amplitude timestream, by ``scipy.optimize.curve_fit``. The fit works in focal-plane
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
from scipy.optimize import curve_fit

MAD_TO_SIGMA = 1.4826
FIT_FIELDS = ("flux", "flux_err", "dxi", "deta", "dxi_err", "deta_err", "offset", "offset_err",
              "snr_fit", "chi2_red", "n_fit_samples", "n_fit_dets", "fit_ok")


@dataclass
class FitConfig:
    window: float = 0.5          # s, half-width of the time window around the median time
    radius: float = np.radians(1.0)
    min_snr: float = 5.0         # keep A0 / sigma_A >= min_snr
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


def beam_shape(track: Track, det_xi, det_eta, dxi=0.0, deta=0.0):
    """Beam-through-filter response, shape (ndet, nt), for a source shifted by (dxi, deta)."""
    ox = det_xi[:, None] - (track.xi[None, :] + dxi)
    oy = det_eta[:, None] - (track.eta[None, :] + deta)
    along = ox * track.along[0] + oy * track.along[1]
    across = -ox * track.along[1] + oy * track.along[0]
    shape = np.interp(along / track.speed, track.lags, track.response, left=0.0, right=0.0)
    return shape * np.exp(-0.5 * (across / track.sigma) ** 2)


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
    rows, cols = np.nonzero(ok)
    y, s = amp[rows, cols], sigma_amp[rows]

    def model(_, a0, dxi, deta, c):
        return a0 * beam_shape(track, det_xi, det_eta, dxi, deta)[rows, cols] + c

    a_start, _ = linear_amplitude(beam_shape(track, det_xi, det_eta)[rows, cols], y, s**-2)
    reach = 3 * track.sigma
    try:
        popt, pcov = curve_fit(model, None, y, p0=[max(a_start, 1e-3), 0.0, 0.0, 0.0], sigma=s,
                               absolute_sigma=True,
                               bounds=([0, -reach, -reach, -np.inf], [np.inf, reach, reach, np.inf]))
    except (RuntimeError, ValueError):
        return out
    errors = np.sqrt(np.diag(pcov)) * inflation * error_scale
    resid = (y - model(None, *popt)) / s
    out.update(flux=popt[0], flux_err=errors[0], dxi=popt[1], deta=popt[2], dxi_err=errors[1],
               deta_err=errors[2], offset=popt[3], offset_err=errors[3],
               snr_fit=popt[0] / errors[0] if errors[0] > 0 else np.nan,
               chi2_red=float(np.sum(resid**2) / max(len(y) - 4, 1)),
               fit_ok=bool(np.all(np.isfinite(errors))))
    return out


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
    ratios = np.asarray(ratios)
    return float(MAD_TO_SIGMA * np.median(np.abs(ratios - np.median(ratios))))
