"""The flare light curve of the reference paper (Clancy et al. 2025, eq. 1).

    S(t) = S_p ((t + t_r - t_p) / t_r)^eta_r    for t_p - t_r <= t <= t_p
    S(t) = S_p ((t_p + t_d - t) / t_d)^eta_d    for t_p < t <= t_p + t_d
    S(t) = 0                                    otherwise

Times in seconds (ctime or any common origin), flux in the units of ``s_peak`` (mJy here).
"""
from __future__ import annotations

import numpy as np


def flare_flux(t, t_peak, s_peak, t_rise, t_decay=None, eta_rise=1.0, eta_decay=1.0):
    """Flux density of a power-law flare at times ``t``; zero outside [t_p - t_r, t_p + t_d]."""
    t_decay = t_rise if t_decay is None else t_decay
    if t_rise <= 0 or t_decay <= 0:
        raise ValueError(f"rise and decay times must be positive, got {t_rise}, {t_decay}")
    t = np.asarray(t, dtype=np.float64)
    rise = np.clip((t + t_rise - t_peak) / t_rise, 0.0, None)
    decay = np.clip((t_peak + t_decay - t) / t_decay, 0.0, None)
    flux = np.where(t <= t_peak, rise**eta_rise, decay**eta_decay) * s_peak
    active = (t >= t_peak - t_rise) & (t <= t_peak + t_decay)
    return np.where(active, flux, 0.0)


def active_window(t_peak, t_rise, t_decay=None):
    """(start, stop) of the interval where the flare's flux is non-zero."""
    t_decay = t_rise if t_decay is None else t_decay
    return t_peak - t_rise, t_peak + t_decay
