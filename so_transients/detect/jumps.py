"""Readout jumps found and removed without touching a source: steps in a detector's level.

A readout jump offsets a detector's timestream from one sample on; a point source, scanned
across at the scan speed, stays in a detector's beam for a fraction of a second and leaves its
level unchanged. So a jump is a change of the *median* level between the ``window`` seconds
before and after a sample, measured on medians of ``block`` seconds: a crossing (0.1-0.3 s) or
a cosmic ray (ms) moves at most one or two of the blocks a window's median is taken over and
so never the median itself. (sotodlib's ``find_jumps`` compares neighbouring samples and also
flags a bright source's crossing, which ``fix_jumps`` then erases.)

A change of the median level by more than ``threshold`` times its own robust spread (over the
detector's whole timestream) is a jump. Its sample is where the mean level changes most within
a window of it (the change of the windows' medians is flat for half a window either side of
a jump), its height the difference of the median levels ``window`` seconds before and after
that sample. Removing it subtracts the height from every later sample.
"""
from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from so_transients.common.robust import mad_std


def _level_changes(rows, n_block, k):
    """Block medians of ``rows`` and, per boundary before block ``b`` (b = k .. nblk - k),
    the median of blocks b..b+k-1 minus that of blocks b-k..b-1."""
    n = rows.shape[1] // n_block
    if n < 2 * k + 1:
        return np.zeros((len(rows), 0))
    m = _median_last(rows[:, :n * n_block].reshape(len(rows), n, n_block))
    windows = _median_last(sliding_window_view(m, k, axis=1))
    return windows[:, k:] - windows[:, :-k]


def _median_last(a):
    """Median along the last axis, whose length is odd (a partition, no copy of a mean)."""
    half = a.shape[-1] // 2
    return np.partition(a, half, axis=-1)[..., half]


def _locate(row, d, n_block, k, threshold):
    """Jumps of one row from its level changes ``d``."""
    spread = mad_std(d)
    if not spread > 0:
        return []
    out = []
    strong = np.abs(d) > threshold * spread
    while strong.any():
        i = int(np.argmax(np.where(strong, np.abs(d), -1)))
        b = i + k                                           # the first block after the change
        lo, hi = max(0, (b - k) * n_block), min(len(row), (b + k) * n_block)
        seg = np.asarray(row[lo:hi], np.float64)
        c = np.cumsum(seg - seg.mean())
        j = np.arange(1, len(seg))
        # the split of the segment that best separates two constant levels (CUSUM)
        split = lo + int(j[np.argmax(np.abs(c[:-1]) / np.sqrt(j * (len(seg) - j)))])
        w = k * n_block
        before = np.median(row[max(0, split - w):split])
        after = np.median(row[split:split + w])
        out.append((split, float(after - before)))
        strong[max(0, i - k):i + k + 1] = False               # one jump per window
    return sorted(out)


def _sizes(sample_rate, window, block):
    """Samples per block and blocks per window, both odd (so that medians are middle values)."""
    n_block = max(1, int(round(block * sample_rate)))
    k = max(3, int(round(window / block)))
    return n_block | 1, k | 1


def find_jumps(row, sample_rate, window=2.0, block=0.25, threshold=8.0):
    """``[(sample, height), ...]`` of the jumps in ``row`` (finite samples, one detector)."""
    n_block, k = _sizes(sample_rate, window, block)
    row = np.asarray(row)
    d = _level_changes(row[None, :], n_block, k)[0]
    return _locate(row, d, n_block, k, threshold) if len(d) else []


def remove_jumps(rows, sample_rate, window=2.0, block=0.25, threshold=8.0):
    """Find and remove the jumps of every row of ``rows`` (rows, nsamp; finite), in place; the
    number of jumps removed per row."""
    n_block, k = _sizes(sample_rate, window, block)
    counts = np.zeros(len(rows), int)
    changes = _level_changes(rows, n_block, k)
    if not changes.shape[1]:
        return counts
    for r, (row, d) in enumerate(zip(rows, changes)):
        for sample, height in _locate(row, d, n_block, k, threshold):
            row[sample:] -= row.dtype.type(height)
            counts[r] += 1
    return counts
