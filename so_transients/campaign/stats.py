"""Detection efficiency statistics: binomial intervals and interpolated thresholds.

* :func:`binomial_interval`: the Jeffreys interval (Bayesian with a Beta(1/2, 1/2) prior), which
  has close to nominal coverage even at 0 or n successes, unlike the normal approximation;
* :func:`monotone`: the efficiency curve made non-decreasing in S_p (weighted isotonic
  regression, pool-adjacent-violators), so a threshold is a single crossing;
* :func:`threshold`: the S_p where that curve first reaches a level, linear between grid points;
* :func:`thresholds`: those thresholds with an uncertainty from a parametric bootstrap of the
  binomial counts (fixed seed).
"""
from __future__ import annotations

import numpy as np
from scipy import stats

LEVELS = (0.1, 0.5, 0.9)


def binomial_interval(k, n, coverage=0.6827):
    """(efficiency k/n, lower, upper) with the Jeffreys interval; arrays broadcast."""
    k, n = np.asarray(k, float), np.asarray(n, float)
    tail = (1 - coverage) / 2
    with np.errstate(invalid="ignore", divide="ignore"):
        eff = np.where(n > 0, k / np.maximum(n, 1), np.nan)
        lo = np.where(k > 0, stats.beta.ppf(tail, k + 0.5, n - k + 0.5), 0.0)
        hi = np.where(k < n, stats.beta.ppf(1 - tail, k + 0.5, n - k + 0.5), 1.0)
    return eff, lo, hi


def monotone(values, weights=None):
    """Weighted least-squares non-decreasing fit to ``values`` (pool adjacent violators)."""
    values = np.asarray(values, float)
    weights = np.ones_like(values) if weights is None else np.asarray(weights, float)
    blocks = []   # [mean, weight, count]
    for v, w in zip(values, weights):
        blocks.append([v, w, 1])
        while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
            v2, w2, c2 = blocks.pop()
            v1, w1, c1 = blocks.pop()
            total = w1 + w2
            mean = (v1 * w1 + v2 * w2) / total if total > 0 else (v1 + v2) / 2
            blocks.append([mean, total, c1 + c2])
    return np.concatenate([np.full(c, m) for m, _, c in blocks]) if blocks else values


def threshold(s_peak, eff, level):
    """S_p at which the non-decreasing curve ``eff(s_peak)`` first reaches ``level``:
    linear interpolation between grid points; ``s_peak[0]`` if the first point is already
    there, NaN if it is never reached."""
    s_peak, eff = np.asarray(s_peak, float), np.asarray(eff, float)
    above = np.flatnonzero(eff >= level)
    if not len(above):
        return np.nan
    i = above[0]
    if i == 0:
        return float(s_peak[0])
    frac = (level - eff[i - 1]) / (eff[i] - eff[i - 1])
    return float(s_peak[i - 1] + frac * (s_peak[i] - s_peak[i - 1]))


def thresholds(s_peak, k, n, levels=LEVELS, n_boot=400, seed=0):
    """{level: (threshold, bootstrap standard deviation)} for counts ``k`` of ``n``."""
    s_peak, k, n = (np.asarray(a, float) for a in (s_peak, k, n))
    order = np.argsort(s_peak)
    s_peak, k, n = s_peak[order], k[order], n[order]
    curve = lambda kk: monotone(kk / np.maximum(n, 1), n)
    rng = np.random.default_rng(seed)
    boots = rng.binomial(n.astype(int), k / np.maximum(n, 1), size=(n_boot, len(n)))
    out = {}
    for level in levels:
        best = threshold(s_peak, curve(k), level)
        draws = np.array([threshold(s_peak, curve(b), level) for b in boots])
        draws = draws[np.isfinite(draws)]
        err = float(np.std(draws)) if len(draws) > 1 and np.isfinite(best) else np.nan
        out[level] = (best, err)
    return out
