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

Before the common-mode (PCA) filtering, the atmosphere changes every detector's level by
several Jy within a window, far more than a jump; :func:`remove_common_jumps` then looks for
jumps in each detector minus its share of the wafer's common mode
(:mod:`so_transients.detect.common_mode`), where only the detector's
own noise is left, and subtracts them from the detector itself. A channel that records no sky
(constant, zero) but still its readout's jumps has no spread of its own: its jumps are those
changes of its level that exceed ``threshold`` times the wafer's typical spread.
:class:`JumpConfig` holds the settings of the ``transient_jumps`` step that runs it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from so_transients.common.robust import mad_std
from so_transients.common.step_config import positive, setting
from so_transients.detect.common_mode import block_medians, block_times, common_share, median_last


def _level_changes(rows, n_block, k):
    """Per boundary before block ``b`` (b = k .. nblk - k) of ``rows``, the median of blocks
    b..b+k-1 minus that of blocks b-k..b-1 (each block's median level)."""
    n = rows.shape[1] // n_block
    if n < 2 * k + 1:
        return np.zeros((len(rows), 0))
    return _window_changes(block_medians(rows, n_block), k)


def _window_changes(m, k):
    windows = median_last(sliding_window_view(m, k, axis=1))
    return windows[:, k:] - windows[:, :-k]


def _locate(row, d, n_block, k, threshold, spread=None):
    """Jumps of one row from its level changes ``d`` (whose spread is ``spread``, default
    measured from ``d``)."""
    spread = mad_std(d) if spread is None else spread
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
    spread = mad_std(changes, axis=1)
    strong = np.any(np.abs(changes) > threshold * spread[:, None], axis=1) & (spread > 0)
    for r in np.flatnonzero(strong):
        row = rows[r]
        for sample, height in _locate(row, changes[r], n_block, k, threshold, spread[r]):
            row[sample:] -= row.dtype.type(height)
            counts[r] += 1
    return counts


@dataclass
class JumpConfig:
    """Settings of the ``transient_jumps`` step (:func:`remove_common_jumps`)."""

    threshold: float = setting(8.0, "", "a jump changes the median level by this many times its spread")
    window: float = setting(2.0, "s", "of median level compared on each side of a jump")
    block: float = setting(0.25, "s", "of each block median")
    chunk_dets: int = setting(64, "", "detectors whose block medians are taken at once (memory)")

    def __post_init__(self):
        positive("transient_jumps", threshold=self.threshold, window=self.window,
                 block=self.block, chunk_dets=self.chunk_dets)
        if self.block * 3 > self.window:
            raise ValueError(f"transient_jumps: window ({self.window} s) must hold at least "
                             f"3 blocks of {self.block} s")


def remove_common_jumps(rows, sample_rate, cfg: JumpConfig = JumpConfig(), live=None):
    """Find the jumps of every row of ``rows`` (rows, nsamp; finite) in the row minus its share
    of the rows' common mode, and remove them from the row, in place; returns the jumps removed
    per row. ``live``: rows (bool) whose median makes the common mode (default: every row
    that is not constant)."""
    n_block, k = _sizes(sample_rate, cfg.window, cfg.block)
    nrows, nsamp = rows.shape
    counts = np.zeros(nrows, int)
    n = nsamp // n_block
    if n < 2 * k + 1 or not nrows:
        return counts
    m = block_medians(rows, n_block, cfg.chunk_dets)
    live = np.ptp(m, axis=1) > 0 if live is None else np.asarray(live, bool)
    if not live.any():
        return counts
    common, gain = common_share(m, live)
    d = _window_changes(m - gain[:, None] * common, k)
    spread = np.array([mad_std(row) for row in d])
    typical = np.median(spread[live & (spread > 0)]) if np.any(live & (spread > 0)) else 0.0
    # a row with no spread of its own (a channel recording no sky) is judged by the wafer's
    spread = np.where(spread > 0, spread, typical)
    common_samples = np.interp(np.arange(nsamp), block_times(n, n_block), common)
    for r in np.flatnonzero(np.any(np.abs(d) > cfg.threshold * spread[:, None], axis=1)):
        residual = rows[r] - gain[r] * common_samples
        for sample, height in _locate(residual, d[r], n_block, k, cfg.threshold, spread[r]):
            rows[r, sample:] -= rows.dtype.type(height)
            counts[r] += 1
    return counts
