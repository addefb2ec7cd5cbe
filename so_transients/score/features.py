"""The score's inputs: numbers every candidate that ``transient_fit`` fitted already carries.

Each feature is a function of the candidate schema's columns
(:mod:`so_transients.common.candidates`) filled by ``transient_find``, ``transient_cuts`` and
``transient_fit``, in both search modes. They describe the candidate's shape rather than its
brightness alone: how its brightest detector compares with the fit (a cosmic ray's one
detector is far brighter than a source could make it), how many detectors and samples took part
against how many the fit says should see it, the spread of hit times about one instant (a
cosmic ray hits every detector at once) and about a drift across the array, opposite-sign
signal nearby, the fit's chi-squared and its constant. A model records the names it was
trained on; adding a feature here leaves the shipped model working (it reads its own list).
"""
from __future__ import annotations

import numpy as np

#: A value no feature takes, given to NaN (a column the step did not fill) before a forest
#: sees it: trees split it off like any other value, the same way in training and use.
MISSING = -1.0e6


def _col(cands, name):
    """Column ``name`` as floats; NaN throughout where the step that fills it did not run."""
    try:
        return np.asarray(cands[name], float)
    except KeyError:
        return np.full(len(np.asarray(cands["snr_max"])), np.nan)


def _ratio(a, b):
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(b != 0, a / b, np.nan)


FEATURES = {
    "snr_max": lambda c: _col(c, "snr_max"),
    "snr_fit": lambda c: _col(c, "snr_fit"),
    "peak_ratio": lambda c: _ratio(_col(c, "snr_max"), _col(c, "snr_fit")),
    "n_dets": lambda c: _col(c, "n_dets"),
    "n_samples": lambda c: _col(c, "n_samples"),
    "samples_per_det": lambda c: _ratio(_col(c, "n_samples"), _col(c, "n_dets")),
    "n_fit_dets": lambda c: _col(c, "n_fit_dets"),
    "hit_share": lambda c: _ratio(_col(c, "n_dets"), _col(c, "n_fit_dets")),
    "aspect_ratio": lambda c: _col(c, "aspect_ratio"),
    "time_rms": lambda c: _col(c, "time_rms"),
    "instant_rms": lambda c: _col(c, "instant_rms"),
    "instant_over_drift": lambda c: _ratio(_col(c, "instant_rms"), _col(c, "time_rms")),
    "opposite_ratio": lambda c: _ratio(_col(c, "opposite_snr"), _col(c, "snr_max")),
    "pol_fraction": lambda c: _col(c, "pol_fraction"),
    "chi2_red": lambda c: _col(c, "chi2_red"),
    "offset_snr": lambda c: _ratio(_col(c, "offset"), _col(c, "offset_err")),
    "duration": lambda c: _col(c, "t_stop") - _col(c, "t_start"),
}


class _Reads(dict):
    """A candidate table that records which columns are read of it (one zero each)."""

    def __getitem__(self, name):
        self.setdefault(name, np.zeros(1))
        return dict.__getitem__(self, name)


def input_columns(names=None) -> tuple:
    """The candidate columns the features ``names`` (default: every one) are computed from,
    in the order they are first read."""
    reads = _Reads()
    for name in (list(FEATURES) if names is None else names):
        FEATURES[name](reads)
    return tuple(reads)


#: The candidate columns every feature together reads
INPUT_COLUMNS = input_columns()


def feature_matrix(cands, names=None) -> np.ndarray:
    """(n_candidates, n_features) array of ``names`` (default: every feature) for the
    candidates ``cands`` (a dict of schema columns, or a table), NaN as :data:`MISSING`."""
    names = list(FEATURES) if names is None else list(names)
    unknown = [n for n in names if n not in FEATURES]
    if unknown:
        raise KeyError(f"unknown score feature(s) {unknown}; known: {sorted(FEATURES)}")
    out = np.column_stack([FEATURES[n](cands) for n in names]) if names else None
    return np.where(np.isfinite(out), out, MISSING)
