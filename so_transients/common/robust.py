"""Robust scatter: the standard deviation of Gaussian noise, insensitive to a few outliers."""
from __future__ import annotations

import numpy as np

MAD_TO_SIGMA = 1.4826


def mad_std(x, axis=-1):
    """1.4826 x median absolute deviation along ``axis`` (0 for an empty 1-d input)."""
    x = np.asarray(x)
    if x.dtype.kind != "f":
        x = x.astype(float)
    if x.size == 0 and x.ndim == 1:
        return 0.0
    med = np.median(x, axis=axis, keepdims=True)
    return MAD_TO_SIGMA * np.median(np.abs(x - med), axis=axis)
