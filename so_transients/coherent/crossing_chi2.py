"""Is a maximum of Z shaped like a source crossing? A chi-squared test over detector groups.

A source crossing the wafer gives each detector's filtered S/N ``x_d`` in proportion to its
weight ``w_d = b_d / sigma_d``, and Z (:mod:`so_transients.coherent.statistic`) is their weighted sum.
The test splits the detectors a position's sum uses into ``bins`` groups that each span
the row's cross-scan offsets alike and the whole crossing, early and late
(:func:`member_groups`), so that a source between rows or a flux changing within the
crossing changes every group's share alike, and compares each group's partial Z with its
share of the whole:

    chi2 = sum_i (Z_i - Z n_i / n)^2,   Z_i = sum_{d in i} w_d x_d / n_i,
    n_i^2 = sum_{d in i} w_d^2,   n^2 = sum_i n_i^2,   Z = sum_i n_i Z_i / n.

For Gaussian noise, with or without a source, chi2 follows the chi-squared law with
``bins - 1`` degrees of freedom; a maximum that a few detectors' spikes make (a glitch; in
a time slide, a glitch's detectors scattered into one sum) puts most of its sum in one
group. Measured on the 20-minute benchmark observation with 6 groups: the time slides'
maxima have median chi2 4.3-4.6 at Z = 4-5 (4.35 expected), but every one from Z = 6 up
has chi2 > 27; the flares from Z = 7 up have chi2 <= 8. These few maxima set the slides'
tail, and so the Z a false-alarm budget needs.

A maximum fails the test when chi2 exceeds the ``1 - chi2_tail`` quantile of its law plus
``(chi2_mismatch x Z)^2`` (a bright source's detectors differ from the model by a few per
cent: gains, beams, pointing).
"""
from __future__ import annotations

import numpy as np
from numba import njit
from scipy.stats import chi2 as chi2_law

from so_transients.coherent.statistic import row_members


def chi2_limit(z, bins, tail, mismatch):
    """The largest chi2 a maximum of normalized Z ``z`` may have: the ``1 - tail`` quantile
    of the chi-squared law with ``bins - 1`` degrees of freedom plus ``(mismatch x z)^2``
    (inf without a test: ``bins`` < 2)."""
    z = np.asarray(z, float)
    if bins < 2:
        return np.full(z.shape, np.inf)
    return chi2_law.isf(tail, bins - 1) + (mismatch * z)**2


def member_groups(indptr, members, across, lags, bins):
    """For each of :func:`so_transients.coherent.statistic.row_members`'s ``members``, its group in
    its row. Each row's detectors are taken in blocks of ``bins`` neighbours across the
    scan (``across``) and each block gives one detector to every group, by the order they
    are crossed (``lags``), rotating from block to block: every group spans the row's
    cross-scan offsets alike and the whole crossing."""
    n = len(members)
    row = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
    by_across = np.lexsort((across[members], row))
    block = np.empty(n, np.int64)
    block[by_across] = (np.arange(n) - indptr[row[by_across]]) // bins
    key = row * (n + 1) + block
    by_lag = np.lexsort((lags[members], key))
    first = np.r_[0, np.flatnonzero(np.diff(key[by_lag])) + 1]
    rank = np.empty(n, np.int64)
    rank[by_lag] = np.arange(n) - np.repeat(first, np.diff(np.r_[first, n]))
    return (rank + block) % bins


def detector_groups(weights, geometry, bins) -> tuple:
    """``(indptr, members, groups)``: the detectors of each row of a map (``weights``: its,
    :func:`so_transients.coherent.statistic.row_weights`; ``geometry``: its
    :class:`so_transients.coherent.statistic.CrossingGeometry`) and their groups
    (:func:`member_groups`), for :func:`crossing_chi2`; every slide of a scan shares them."""
    indptr, members = row_members(weights)
    return indptr, members, member_groups(indptr, members, np.asarray(geometry.across),
                                          np.asarray(geometry.lag_samples), max(bins, 1))


def crossing_chi2(snr, weights, groups, bins, shifts, rows, samples, sign=1.0, cyclic=True):
    """chi2 of each map position (``rows`` indices, ``samples``) of the map of ``sign`` x
    ``snr`` whose detectors are read at ``(t + shifts[d]) % nsamp`` (``shifts``: the lags,
    plus a time slide's offsets; without ``cyclic``, the data's map: only the detectors
    crossed inside ``snr`` count); ``weights``: the map's, ``groups``: their
    :func:`detector_groups`. NaN without ``bins`` >= 2."""
    if bins < 2:
        return np.full(len(rows), np.nan)
    indptr, members, groups = groups
    out = np.zeros(len(rows))
    _chi2(np.asarray(snr), np.ascontiguousarray(weights), indptr, members, groups, bins,
          np.asarray(shifts, np.int64), np.asarray(rows, np.int64),
          np.asarray(samples, np.int64), float(sign), bool(cyclic), out)
    return out


@njit(cache=True, nogil=True)
def _chi2(snr, weights, indptr, members, groups, bins, shifts, rows, samples, sign, cyclic,
          out):
    nsamp = snr.shape[1]
    part, norm2 = np.zeros(bins), np.zeros(bins)
    for k in range(len(rows)):
        r, t = rows[k], samples[k]
        part[:] = 0.0
        norm2[:] = 0.0
        for i in range(indptr[r], indptr[r + 1]):
            d, g = members[i], groups[i]
            if not cyclic and not 0 <= t + shifts[d] < nsamp:
                continue
            w = weights[r, d]
            v = snr[d, (t + shifts[d]) % nsamp]
            if np.isfinite(v):
                part[g] += sign * w * v
            norm2[g] += w * w
        total = np.sqrt(norm2.sum())
        z = part.sum() / total
        c = 0.0
        for g in range(bins):
            if norm2[g] > 0:
                n = np.sqrt(norm2[g])
                c += (part[g] / n - z * n / total) ** 2
        out[k] = c
