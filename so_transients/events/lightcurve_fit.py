"""Fits to an event's light curve: the paper's eq. 1 per band, and the spectral index.

:func:`fit_flare` fits :func:`so_transients.common.flare_model.flare_flux` (peak flux, peak time, rise
and decay times; the power-law indices held at ``eta`` unless ``fit_indices``) to forced-
photometry points by bounded least squares from several starting rise times, and returns
the parameters with errors from the covariance at the best fit (scaled by the reduced chi^2
when above 1). :func:`spectral_index` combines simultaneous crossings of two bands (the same
wafer's pixels see both MF, or both UHF, bands at once) into ``alpha`` of ``S ~ nu^alpha``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from so_transients.common.bands import CENTER_GHZ
from so_transients.common.flare_model import flare_flux
from so_transients.common.step_config import setting

#: Parameters of eq. 1 in the order :func:`fit_flare` reports them.
FLARE_PARAMS = ("s_peak", "t_peak", "t_rise", "t_decay", "eta_rise", "eta_decay")


@dataclass
class FlareFitConfig:
    fit_indices: bool = setting(False, "", "fit eta_rise and eta_decay too (else held at eta)")
    eta: float = setting(1.0, "", "the indices when they are held (the paper's flares: 1)")
    min_points: int = setting(4, "", "fewer light-curve points: no fit")
    min_time_s: float = setting(0.05, "s", "the rise and decay times at least this ...")
    max_time_s: float = setting(3600.0, "s", "... and at most this")


def _model(p, t, cfg):
    s_peak, t_peak, t_rise, t_decay = p[:4]
    eta_r, eta_d = (p[4], p[5]) if cfg.fit_indices else (cfg.eta, cfg.eta)
    return flare_flux(t, t_peak, s_peak, t_rise, t_decay, eta_r, eta_d)


def _start_points(t, flux, err, cfg):
    """Starting parameters: the peak at the most significant point, rise and decay times
    from the shortest allowed up to the light curve's span."""
    best = int(np.argmax(flux / err))
    span = max(float(np.ptp(t)), 1.0)
    for tau in np.geomspace(max(cfg.min_time_s, 0.25), min(span, cfg.max_time_s), 6):
        p = [max(flux[best], err[best]), t[best], tau, tau]
        yield p + [cfg.eta, cfg.eta] if cfg.fit_indices else p


def fit_flare(t, flux, flux_err, cfg: FlareFitConfig | None = None) -> dict:
    """Eq. 1 fitted to light-curve points (ctime s, mJy, mJy). Returns each of
    :data:`FLARE_PARAMS` and ``<name>_err`` (NaN when held or unconstrained), ``chi2_red``,
    ``n_points`` and ``fit_ok``."""
    cfg = cfg or FlareFitConfig()
    t, flux, err = (np.asarray(v, float) for v in (t, flux, flux_err))
    good = np.isfinite(t) & np.isfinite(flux) & np.isfinite(err) & (err > 0)
    t, flux, err = t[good], flux[good], err[good]
    out = {k: np.nan for k in FLARE_PARAMS}
    out.update({f"{k}_err": np.nan for k in FLARE_PARAMS}, chi2_red=np.nan,
               n_points=int(len(t)), fit_ok=False)
    n_par = 6 if cfg.fit_indices else 4
    if len(t) < max(cfg.min_points, n_par):
        return out
    # times from the most significant point: on absolute ctimes (1.7e9 s) the finite-
    # difference steps of the peak time would be tens of seconds
    t_ref = float(t[np.argmax(flux / err)])
    t = t - t_ref
    lower = [0.0, t.min() - cfg.max_time_s, cfg.min_time_s, cfg.min_time_s, 0.1, 0.1][:n_par]
    upper = [np.inf, t.max() + cfg.max_time_s, cfg.max_time_s, cfg.max_time_s, 5.0, 5.0][:n_par]
    resid = lambda p: (_model(p, t, cfg) - flux) / err
    best = None
    for p0 in _start_points(t, flux, err, cfg):
        p0 = np.clip(p0, lower, upper)
        res = least_squares(resid, p0, bounds=(lower, upper), x_scale="jac")
        if best is None or res.cost < best.cost:
            best = res
    dof = max(len(t) - n_par, 1)
    chi2_red = 2 * best.cost / dof
    try:
        cov = np.linalg.inv(best.jac.T @ best.jac) * max(chi2_red, 1.0)
        errors = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        errors = np.full(n_par, np.nan)
    params = list(best.x) + ([] if cfg.fit_indices else [cfg.eta, cfg.eta])
    params[1] += t_ref
    errors = list(errors) + ([] if cfg.fit_indices else [np.nan, np.nan])
    for k, name in enumerate(FLARE_PARAMS):
        out[name], out[f"{name}_err"] = float(params[k]), float(errors[k])
    out.update(chi2_red=float(chi2_red),
               fit_ok=bool(best.success and np.all(np.isfinite(errors[:n_par]))))
    return out


def spectral_index(flux_a, err_a, flux_b, err_b, band_a, band_b, min_snr):
    """``(alpha, alpha_err, n)``: the inverse-variance weighted spectral index of pairs of
    simultaneous measurements in bands ``band_a`` and ``band_b`` (``S ~ nu^alpha`` at the
    bands' centre frequencies), from the pairs where both fluxes reach ``min_snr``; NaN and
    0 when there is none."""
    fa, ea, fb, eb = (np.asarray(v, float) for v in (flux_a, err_a, flux_b, err_b))
    ok = (fa >= min_snr * ea) & (fb >= min_snr * eb) & (ea > 0) & (eb > 0)
    if not ok.any():
        return np.nan, np.nan, 0
    lever = np.log(CENTER_GHZ[band_b] / CENTER_GHZ[band_a])
    alpha = np.log(fb[ok] / fa[ok]) / lever
    sigma = np.hypot(ea[ok] / fa[ok], eb[ok] / fb[ok]) / abs(lever)
    w = sigma**-2.0
    return float(np.sum(w * alpha) / np.sum(w)), float(np.sum(w) ** -0.5), int(ok.sum())
