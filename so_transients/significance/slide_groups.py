"""Time slides that move groups of detectors together, so that slides share their sums.

A time slide shifts each detector's S/N cyclically within the scan. When the detectors are
cut into ``G`` groups and a slide shifts every detector of a group alike, its map is a sum of
``G`` shifted *partial maps*, ``P_g[r, t] = sum_{d in g} w[r, d] snr[d, t + lag_d]``, which
every slide shares: a slide's map costs ``G`` adds per position instead of one per detector
within reach of the row (145-155 on an f090 wafer), and the partial maps cost one map,
once per scan. Their sum with every group at offset 0 is the data's own map, summed
cyclically (:func:`group_sum`), so the data's map costs only that sum.

What a group keeps together stays coherent. A real source of statistic ``Z`` leaves about
``Z / G`` in each group's part (the groups are random, so each holds about ``1 / G`` of any
row's detectors), where per-detector slides leave one detector's share (``Z / N_eff``, with
``N_eff`` about 40 at f090): with 8 groups a 3 Jy source filled the slides with parts at
Z = 7 and more. So the data's own maxima from the gate (``slide_gate``, Z = 6 by default:
what is left of a source below it, at most 6 / G in a group's part, 1.5 with the default 4
groups, cannot lift the slides' noise to a false-alarm budget's Z) are gated out of what
is slid first (:func:`gate_maxima`): every detector within reach of such a maximum's row
has its S/N zeroed within ``half`` samples of the time the position passes it, and the
partial maps are corrected where those samples were. Noise reaches the gate a few times a
wafer-band-day (its maxima from Z = 6 are the paper's rate), each gate taking a second of
about 150 detectors out of the slides; a single detector's spike, which the background
must keep, is not gated. A group's noise keeps the correlations of its own detector pairs
(``1 / G`` of them), which the slides' measured spread takes in. The groups' offsets are
kept apart, by at least half of the scan's usable range over ``G``, so that no two groups
line up again.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from so_transients.coherent.statistic import row_members, shift_add, time_slide_offsets


def slide_groups(live, n_groups, rng) -> np.ndarray | None:
    """(ndet,) group of each detector: the ``live`` ones (bool, (ndet,)) a random partition
    into ``n_groups`` groups of equal size (to one), the others spread over them; None
    (every detector its own group) for ``n_groups = 0`` or fewer live detectors than
    ``2 n_groups``."""
    live = np.asarray(live, bool)
    n_live = int(live.sum())
    if n_groups <= 0 or n_live < 2 * n_groups:
        return None
    out = np.arange(len(live)) % n_groups
    out[live] = rng.permutation(np.arange(n_live) % n_groups)
    return out


def scan_groups(live, n_groups, nsamp, min_shift, window, rng) -> np.ndarray | None:
    """:func:`slide_groups` for a scan of ``nsamp`` samples, or None (each detector slid on
    its own) when the scan is too short to keep the groups apart
    (:func:`min_group_samples`)."""
    groups = slide_groups(live, n_groups, rng)
    if groups is not None and nsamp < min_group_samples(n_groups, min_shift, window):
        return None
    return groups


def group_offsets(groups, ndet, nsamp, min_shift, rng, n_slides=None) -> np.ndarray:
    """(ndet,) cyclic offsets (samples) of one slide, or (n_slides, ndet) of that many:
    each group's detectors shifted alike, by an offset in ``[min_shift, nsamp -
    min_shift)``; the groups' offsets are drawn one in each of ``G`` equal parts of that
    range (in random order), within its first half, so any two differ by at least half a
    part. ``groups`` None (every detector its own group): independent offsets
    (:func:`so_transients.coherent.statistic.time_slide_offsets`)."""
    if groups is None:
        return time_slide_offsets(ndet, nsamp, min_shift, rng, n_slides)
    n_groups = int(np.max(groups)) + 1
    part = (nsamp - 2 * min_shift) // n_groups
    if part < 2:
        raise ValueError(f"a scan of {nsamp} samples is too short for {n_groups} slide "
                         f"groups at least {min_shift} samples from 0")
    shape = (1 if n_slides is None else n_slides, n_groups)
    order = rng.permuted(np.broadcast_to(np.arange(n_groups), shape), axis=1)
    offsets = min_shift + part * order + rng.integers(0, part // 2 + 1, size=shape)
    offsets = offsets[:, groups]
    return offsets[0] if n_slides is None else offsets


def min_group_samples(n_groups, min_shift, window) -> int:
    """The shortest scan (samples) whose slide groups' offsets stay at least two
    ``window``s (beam crossing times) apart: shorter scans slide each detector on its
    own."""
    return 2 * min_shift + 4 * window * max(n_groups, 1)


def partial_maps(snr, weights, lags, groups) -> np.ndarray:
    """``(G * nrow, nsamp)`` float32: row ``g * nrow + r`` is group ``g``'s share of row
    ``r`` of the map, ``sum_{d in g} weights[r, d] * snr[d, (t + lags[d]) % nsamp]``
    (cyclic: a slide reads it shifted; ``snr`` finite)."""
    nrow, nsamp = weights.shape[0], snr.shape[1]
    groups = np.asarray(groups)
    n_groups = int(groups.max()) + 1
    out = np.zeros((n_groups, nrow, nsamp), np.float32)
    w32 = np.ascontiguousarray(weights, np.float32)
    shifts = np.asarray(lags, np.int64)
    has_weight = np.any(weights != 0, axis=0)
    for g in range(n_groups):
        used = np.flatnonzero((groups == g) & has_weight)
        shift_add(snr, w32, used, shifts, out[g])
    return out.reshape(n_groups * nrow, nsamp)


def group_sum(partial, n_groups) -> np.ndarray:
    """(nrow, nsamp): the sum of the ``n_groups`` groups' partial maps ``partial``
    (:func:`partial_maps`): the whole map, summed cyclically, unnormalized."""
    return partial.reshape(n_groups, -1, partial.shape[1]).sum(axis=0)


def gate_maxima(snr, weights, lags, rows, samples, half, partial=None, groups=None,
                in_place=False):
    """A copy of ``snr`` (ndet, nsamp) with every detector that has a weight in row
    ``rows[k]`` zeroed within ``half`` samples of ``samples[k] + lags[d]``, where the map
    position (``rows[k]``, ``samples[k]``) passes it, cyclically (as the cyclic map sums:
    a source crossing at one end of the scan is gated where it is). ``partial``: the
    :func:`partial_maps` of ``snr`` in ``groups``, made the copy's in place (only the
    gated samples' terms are touched). ``in_place``: ``snr`` itself is gated and
    returned."""
    out = snr if in_place else np.array(snr, copy=True)
    indptr, members = row_members(weights)
    if partial is None:
        partial, groups = np.zeros((0, 0), np.float32), np.zeros(len(out), np.int64)
    det_ptr, det_rows = row_members(np.asarray(weights).T)       # each detector's rows
    _gate(out, indptr, members, np.asarray(lags, np.int64), np.asarray(rows, np.int64),
          np.asarray(samples, np.int64), int(half), partial, np.asarray(groups, np.int64),
          np.ascontiguousarray(weights, np.float32), det_ptr, det_rows)
    return out


@njit(cache=True, nogil=True)
def _gate(snr, indptr, members, lags, rows, samples, half, partial, groups, weights, det_ptr,
          det_rows):
    nsamp = snr.shape[1]
    nrow = weights.shape[0]
    for k in range(len(rows)):
        r = rows[k]
        for i in range(indptr[r], indptr[r + 1]):
            d = members[i]
            centre = samples[k] + lags[d]
            for u in range(centre - half, centre + half + 1):
                u %= nsamp
                v = snr[d, u]
                if v == 0.0:
                    continue
                snr[d, u] = 0.0
                if partial.shape[0] == 0:
                    continue
                t, base = (u - lags[d]) % nsamp, groups[d] * nrow
                for j in range(det_ptr[d], det_ptr[d + 1]):
                    partial[base + det_rows[j], t] -= weights[det_rows[j], d] * v
