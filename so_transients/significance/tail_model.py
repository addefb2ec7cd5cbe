"""A Gaussian-like model of the tail of a noise statistic, to count beyond what was measured.

With a few hours of noise there are too few values far in the tail to count down to rates of
a few per hundred hours. Above ``x0`` the tail is modelled as ``N(>x) = N(>x0) exp(-(x^2 -
x0^2) / 2 s^2)`` with ``s^2`` its maximum-likelihood value ``mean(x^2 - x0^2) / 2``
(Gaussian noise has ``N(>x)`` proportional to ``exp(-x^2 / 2) / x``, close to this with s =
1; correlated or glitchy noise gives s > 1). Used for the campaign's thresholds at the
paper's false-detection rate (fitted S/N of noise candidates) and for the false-alarm rate
of ``transient_significance`` (Z maxima of the sign-inverted data).
"""
from __future__ import annotations

import numpy as np


def tail_fit(snr, x0):
    """``(n0, s^2)``: the number of candidates above ``x0`` and the tail's maximum-likelihood
    scale (NaN below 5 candidates)."""
    snr = np.asarray(snr, float)
    tail = snr[np.isfinite(snr) & (snr > x0)]
    s2 = np.mean(tail**2 - x0**2) / 2 if len(tail) >= 5 else np.nan
    return len(tail), s2


def tail_threshold(snr, wafer_hours, target, x0=3.0):
    """Fitted-S/N threshold where the modelled noise rate above it is ``target`` per
    wafer-band-hour, from the noise candidates' fitted S/N ``snr``; ``(threshold, s, n0)``
    with the tail's scale and the number above ``x0`` (NaN threshold below 5 candidates)."""
    n0, s2 = tail_fit(snr, x0)
    if not np.isfinite(s2):
        return np.nan, np.nan, n0
    x2 = x0**2 + 2 * s2 * np.log(max(n0 / (target * wafer_hours), 1.0))
    return float(np.sqrt(x2)), float(np.sqrt(s2)), n0


def model_count_above(x, snr, x0=3.0):
    """The tail model's expected number of values above ``x`` (a number or an array; NaN
    below 5 values above ``x0``)."""
    n0, s2 = tail_fit(snr, x0)
    x = np.asarray(x, float)
    out = n0 * np.exp(-(x**2 - x0**2) / (2 * s2)) if np.isfinite(s2) else np.full(x.shape, np.nan)
    return float(out) if out.ndim == 0 else out
