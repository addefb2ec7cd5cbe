"""A wafer's common mode at the resolution of block medians, and each detector's share of it.

Before the common-mode (PCA) filtering the atmosphere moves every detector by several Jy, far
more than its own noise, a readout jump or a crossing. Medians of ``block`` seconds of each
detector are blind to a crossing (a fraction of a second) and to a cosmic ray; their median
over the live detectors is the wafer's common mode, and each detector's share of it is the
common mode times a gain fitted by least squares to the changes between blocks (a jump moves
one such change only). What a detector does beyond its share is its own: noise, the
atmosphere's gradients across the wafer, jumps (:func:`so_transients.detect.jumps.remove_common_jumps`)
and sources (:func:`mask_excursions`, which hides them from the PCA's model signal).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.lib.stride_tricks import sliding_window_view

from so_transients.common.robust import mad_std
from so_transients.common.step_config import positive, setting


def median_last(a):
    """Median along the last axis, whose length is odd (a partition, no copy of a mean)."""
    half = a.shape[-1] // 2
    return np.partition(a, half, axis=-1)[..., half]


def block_medians(rows, n_block, chunk=64):
    """Median of each row's consecutive ``n_block`` samples, (rows, nsamp // n_block) float64,
    ``chunk`` rows at a time (the partition copies them)."""
    nrows, nsamp = rows.shape
    n = nsamp // n_block
    out = np.empty((nrows, n), np.float64)
    for start in range(0, nrows, chunk):
        part = rows[start:start + chunk, :n * n_block]
        out[start:start + chunk] = median_last(part.reshape(len(part), n, n_block))
    return out


def common_share(m, live):
    """``(common, gain)``: the median over the ``live`` rows of block medians ``m`` and each
    row's least-squares gain on it, fitted to the changes between blocks."""
    common = np.median(m[live], axis=0)
    dc = np.diff(common)
    gain = (np.diff(m, axis=1) @ dc) / max(float(dc @ dc), 1e-300)
    return common, gain


def block_times(n, n_block):
    """Sample index of the middle of each of ``n`` blocks."""
    return (np.arange(n) + 0.5) * n_block


@dataclass
class ExcursionConfig:
    """Settings of the ``transient_pca_mask`` step (:func:`mask_excursions`)."""

    signal: str = setting("lpf_signal", "", "the PCA's model signal (pca_filter's model_signal)")
    threshold: float = setting(5.0, "", "samples this many times a detector's spread beyond its baseline")
    block: float = setting(0.25, "s", "of each block median")
    window: float = setting(2.0, "s", "of blocks whose median is the baseline beyond the share")
    buffer: float = setting(0.2, "s", "masked around each excursion")
    chunk_dets: int = setting(64, "", "detectors whose block medians are taken at once (memory)")

    def __post_init__(self):
        positive("transient_pca_mask", threshold=self.threshold, block=self.block,
                 window=self.window, buffer=self.buffer, chunk_dets=self.chunk_dets)


def mask_excursions(rows, sample_rate, cfg: ExcursionConfig = ExcursionConfig(), live=None):
    """Replace, in place, each row's brief excursions beyond its baseline (its share of the
    common mode plus a running median of the rest over ``window``) by the baseline: samples
    beyond ``threshold`` times the row's robust spread about it, and ``buffer`` seconds around
    them. ``rows``: (rows, nsamp), finite. Returns ``(counts, limits)``: the samples replaced
    per row, and each row's limit (``threshold`` times its spread, in the rows' units; inf
    where nothing could be replaced), beyond which an excursion is hidden."""
    nrows, nsamp = rows.shape
    counts = np.zeros(nrows, int)
    limits = np.full(nrows, np.inf)
    n_block = max(1, int(round(cfg.block * sample_rate))) | 1
    k = max(3, int(round(cfg.window / cfg.block))) | 1
    n = nsamp // n_block
    if n < k or not nrows:
        return counts, limits
    m = block_medians(rows, n_block, cfg.chunk_dets)
    live = np.ptp(m, axis=1) > 0 if live is None else np.asarray(live, bool)
    if not live.any():
        return counts, limits
    common, gain = common_share(m, live)
    rest = median_last(sliding_window_view(m - gain[:, None] * common, k, axis=1))
    half = k // 2
    t_rest = block_times(n, n_block)[half:n - half]
    common_s = np.interp(np.arange(nsamp), block_times(n, n_block), common).astype(np.float32)
    grow = max(1, int(round(cfg.buffer * sample_rate)))
    sub = np.arange(0, nsamp, 7)          # the spread is measured on every 7th sample
    base = np.empty(nsamp)
    for r in range(nrows):
        spread = mad_std(rows[r, sub] - (gain[r] * common_s[sub] + np.interp(
            sub, t_rest, rest[r]).astype(np.float32)))
        if spread > 0:
            _baseline(gain[r], common_s, t_rest, rest[r], base)
            limits[r] = cfg.threshold * spread
            counts[r] = _replace_excursions(rows[r], base, limits[r], grow)
    return counts, limits


@njit(cache=True, nogil=True)
def _baseline(gain, common_s, t_rest, rest, out):
    """A row's baseline at every sample into ``out`` (float64): ``gain x common_s`` plus
    ``rest`` linearly interpolated from the increasing sample positions ``t_rest``, exactly
    as ``np.interp`` does and then rounded to float32."""
    last = len(t_rest) - 1
    j = 0
    for s in range(len(out)):
        x = float(s)
        if x <= t_rest[0]:
            value = rest[0]
        elif x >= t_rest[last]:
            value = rest[last]
        else:
            while t_rest[j + 1] <= x:
                j += 1
            if t_rest[j] == x:
                value = rest[j]
            else:
                slope = (rest[j + 1] - rest[j]) / (t_rest[j + 1] - t_rest[j])
                value = slope * (x - t_rest[j]) + rest[j]
        out[s] = gain * np.float64(common_s[s]) + np.float64(np.float32(value))


@njit(cache=True, nogil=True)
def _replace_excursions(row, base, limit, grow):
    """In place, the samples of ``row`` more than ``limit`` from ``base``, and ``grow``
    samples around them, set to ``base``; returns how many (one pass over the row)."""
    nsamp = len(row)
    count = 0
    s = 0
    while s < nsamp:
        if not abs(np.float64(row[s]) - base[s]) > limit:
            s += 1
            continue
        start = max(0, s - grow)
        end = min(nsamp, s + grow + 1)
        t = s + 1
        while t < min(nsamp, end + grow):
            if abs(np.float64(row[t]) - base[t]) > limit:
                end = min(nsamp, t + grow + 1)
            t += 1
        for j in range(start, end):
            row[j] = np.float32(base[j])
        count += end - start
        s = end
    return count
