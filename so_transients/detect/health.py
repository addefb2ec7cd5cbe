"""A group's health: how its detectors share the weight of every map and fit.

Each detector weighs as ``1 / sigma_amp^2`` (its filtered amplitude's noise) in the coherent
map, the time slides and the beam fit. When the selection and the weights agree, the
effective number of detectors, ``(sum w)^2 / sum w^2``, is most of those used: 0.78 of them
for a log-normal noise scatter of 25 % (``exp(-4 s^2)``), 0.37 for 50 %. When a few channels
weigh far more than the rest (a dead channel whose amplitude noise was measured a thousand
times too low), it collapses to a handful, and every flux and position is theirs: the
search is then confident and wrong. :func:`weight_health` measures it; :func:`health_warnings`
says, in words, what is out of range.
"""
from __future__ import annotations

import numpy as np

#: A group whose effective number of detectors is below this fraction of those used ...
MIN_EFFECTIVE_FRACTION = 0.25
#: ... or one of whose detectors carries more than this share of the weight, is unhealthy
MAX_WEIGHT_SHARE = 0.05


def weight_health(sigma_amp, used) -> dict:
    """``n_used``, ``n_eff`` (effective number of detectors), ``eff_fraction`` (n_eff over
    n_used) and ``max_weight_share`` (the largest detector's share of the weight) of the
    detectors ``used`` (bool), weighted ``1 / sigma_amp^2``."""
    sigma = np.asarray(sigma_amp, float)
    used = np.asarray(used, bool) & (sigma > 0) & np.isfinite(sigma)
    n = int(used.sum())
    if not n:
        return {"n_used": 0, "n_eff": 0.0, "eff_fraction": np.nan, "max_weight_share": np.nan}
    w = sigma[used] ** -2.0
    n_eff = float(w.sum() ** 2 / np.sum(w ** 2))
    return {"n_used": n, "n_eff": n_eff, "eff_fraction": n_eff / n,
            "max_weight_share": float(w.max() / w.sum())}


def health_warnings(health, min_fraction=MIN_EFFECTIVE_FRACTION,
                    max_share=MAX_WEIGHT_SHARE) -> list:
    """What is out of range in a :func:`weight_health` result, in words ([] when healthy)."""
    out = []
    if health["n_used"] and health["eff_fraction"] < min_fraction:
        out.append(f"effective number of detectors {health['n_eff']:.1f} of "
                   f"{health['n_used']} used (below {min_fraction:g} of them)")
    if health["n_used"] >= 1 / max_share and health["max_weight_share"] > max_share:
        out.append(f"one detector carries {100 * health['max_weight_share']:.0f} % of the "
                   f"weight (above {100 * max_share:g} %)")
    return out
