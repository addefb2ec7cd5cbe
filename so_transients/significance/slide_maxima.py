"""The high local maxima of a time slide's map, found coarse to fine.

A time slide's map is the background of ``far`` only where it is high: its local maxima at
least the slide floor. :class:`SlideSearch` finds them without summing the whole map. It
first sums a coarse map (the screen), every other row and every ``step``-th sample
(``step``: one beam crossing time), for about ``1 / (2 step)`` of the full sum's
multiply-adds, and fewer again: each row sums only the detectors within
:data:`SCREEN_REACH` beam sigmas (99.6 % of its weight^2; the map's rows reach 3, half
as many detectors again; a row that would keep less than :data:`SCREEN_KEEP` of it, beside
dead detectors, sums as far as the map's), read as 16-bit integers in units of
:data:`QUANTUM` (S/N to 0.002, half the bytes of float32; a spike beyond S/N 128 is
clipped). A screen value is the full map's at its position to about 0.06 in Z. With
grouped slides (:mod:`so_transients.significance.slide_groups`) the screen sums the groups' partial maps
instead, every detector within the map's reach, each read as 16-bit integers in units of
1/256 of its own spread (:func:`term_quanta`): the full map's value to 0.001 in Z. Around
each coarse position at least :data:`REFINE` x the threshold it then sums the full map
(exactly, as :func:`so_transients.coherent.statistic.coherent_map`), one row and ``step`` samples
either side (the core) and, for the local-maximum test, the neighbourhood of the core; the
maxima are those of the core, at the full map's values.

A maximum at least the threshold is missed only when every coarse position within one row
and ``step`` samples of it is below ``REFINE`` x the threshold. Z's response to a source and
the filtered noise's peaks alike are about a beam wide across and a beam crossing time
along (times sqrt(2)): the nearest coarse position, at most one row (0.8 beam sigma) and
half a crossing time away, keeps 80-85 % of a peak, and :data:`REFINE` = 0.75 leaves room
for the noise's own irregularity and the screen's 0.06. The refining threshold is fixed,
so a maximum of height ``Z`` is missed only when every such coarse position is below
``REFINE x floor / Z`` of it: misses gather just above the floor (on the 20-minute
benchmark scans, 1 of 953 maxima from Z = 4.5, at 4.59, one detector's spike that the
background leaves out anyway; at 0.7, none, for 1.3x the cost of a slide), and a maximum
at a false-alarm budget's Z of 6-7 would need a drop to half its height.
``tests/test_slide_maxima.py`` checks the maxima against the full map's on filtered
noise, and ``studies/slide_search.py`` on a simulated observation. Where much of the
map would need refining (a threshold near the noise), the full map is summed instead.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from so_transients.coherent.statistic import (
    add_slice, is_top, local_maxima, measured_scale, row_members, row_weights, shift_add,
    term_shares
)
from so_transients.significance.slide_groups import partial_maps

#: Coarse positions at least this share of the threshold are refined.
REFINE = 0.75
#: The screen's rows sum the detectors within this many beam sigmas (the map's: 3)...
SCREEN_REACH = 2.0
#: ... unless that keeps less than this share of the row's weight^2.
SCREEN_KEEP = 0.9
#: The screen reads each detector's S/N as 16-bit integers in this unit.
QUANTUM = 2.0**-8
#: Beyond this share of the map to refine, the whole map is summed instead: a refined
#: position's detector samples are read from scattered addresses, 50-70x the cost of a
#: position of the whole map's streamed sum (measured on the 20-minute benchmark scans).
MAX_REFINED = 0.01


class SlideSearch:
    """The maxima of the time slides of one scan's S/N ``snr`` (finite, (ndet, nsamp)):
    what every slide shares (weights, the coarse sampling's phases) is prepared once.

    ``groups`` (ndet,): slides shift the detectors of a group alike
    (:mod:`so_transients.significance.slide_groups`), and the search sums the groups' partial maps (its
    terms) instead of the detectors; its screen then sums every detector within the map's
    reach, each partial map read as 16-bit integers in units of 1/256 of its spread
    (:func:`term_quanta`); ``partial``: those partial maps of ``snr`` when the caller has
    them (:func:`so_transients.significance.slide_groups.partial_maps`). ``None``: every detector is its
    own term."""

    def __init__(self, snr, geometry, rows, beam_sigma, sigma_amp, live, window, groups=None,
                 partial=None):
        self.snr, self.geometry, self.rows, self.window = snr, geometry, rows, int(window)
        self.lags = geometry.lag_samples
        self.weights, self.norm = row_weights(geometry, rows, beam_sigma, sigma_amp, live)
        self.norm32 = self.norm.astype(np.float32)
        # a slide's Z where it was summed: where ``stamp`` is +-the slide's number
        shape = (len(rows), snr.shape[1])
        self.z, self.stamp, self.slide = np.empty(shape, np.float32), np.zeros(shape, np.int32), 0
        self.step = geometry.crossing_samples(beam_sigma)
        self.scale = None          # the slides' measured spread (unnormalized Z)
        self.groups = None if groups is None else np.asarray(groups)
        if self.groups is None:
            self._detector_terms(beam_sigma, sigma_amp, live)
        else:
            self._group_terms(partial)
        self.indptr, self.members = row_members(self.term_weights)
        self.detector_members = row_members(self.weights)
        self.coarse_used = np.flatnonzero(np.any(self.coarse_weights != 0, axis=0))
        # the screen sums of Z = 1 (inf on rows without detectors: no level reached)
        self.coarse_levels = np.where(self.coarse_norm > 0, self.coarse_norm, np.inf)
        self._screen = None

    def _detector_terms(self, beam_sigma, sigma_amp, live):
        """Every detector a term; the screen reads them as 16-bit integers, within
        :data:`SCREEN_REACH`."""
        self.terms, self.terms32 = self.snr, np.asarray(self.snr, np.float32)
        self.term_weights = self.weights
        self.weights32 = self.weights.astype(np.float32)
        ndet = self.snr.shape[0]
        self.screen_terms = np.arange(ndet)
        self.phases = sample_phases(self.snr, self.step, np.full(ndet, QUANTUM),
                                    self.screen_terms)
        screen, norm = row_weights(self.geometry, self.rows, beam_sigma, sigma_amp, live,
                                   SCREEN_REACH)
        short = norm**2 < SCREEN_KEEP * self.norm**2
        screen[short], norm[short] = self.weights[short], self.norm[short]
        self.coarse_weights = np.ascontiguousarray(screen[::2] * QUANTUM, np.float32)
        self.coarse_norm = norm[::2].astype(np.float32)

    def _group_terms(self, partial=None):
        """Each group's share of each row a term (row ``g * nrow + r``, its lags included);
        the screen reads them as they are."""
        nrow = len(self.rows)
        self.terms = partial if partial is not None else partial_maps(
            self.snr, self.weights, self.lags, self.groups)
        self.terms32 = self.terms
        n_groups = self.terms.shape[0] // nrow
        select = np.tile(np.eye(nrow, dtype=np.float32), (1, n_groups))   # row r: g*nrow + r
        self.term_weights = self.weights32 = select
        # the screen's rows are every other row: only their terms are read by it
        self.screen_terms = np.flatnonzero(np.tile(np.arange(nrow) % 2 == 0, n_groups))
        quantum = term_quanta(self.terms, self.screen_terms)
        self.phases = sample_phases(self.terms, self.step, quantum, self.screen_terms)
        self.coarse_weights = np.ascontiguousarray(select[::2][:, self.screen_terms]
                                                   * quantum[None, :], np.float32)
        self.coarse_norm = self.norm32[::2]
        # a group's offset is read from one of its detectors
        self.leaders = np.array([np.flatnonzero(self.groups == g)[0]
                                 for g in range(n_groups)])
        self.term_group = np.repeat(np.arange(n_groups), nrow)

    def term_shifts(self, offsets):
        """(nterm,) cyclic shifts (samples, in [0, nsamp)) of the terms in the slide
        ``offsets`` (per detector; alike within a group)."""
        nsamp = self.snr.shape[1]
        offsets = np.asarray(offsets, np.int64)
        if self.groups is None:
            return (self.lags + offsets) % nsamp
        return offsets[self.leaders][self.term_group] % nsamp

    def maxima(self, offsets, floor):
        """``(rows, samples, z, scale)``: the local maxima of the slide ``offsets``'s map
        (unnormalized Z, as :func:`so_transients.coherent.statistic.coherent_map`'s, float32 sums) at
        least ``floor`` x ``scale`` in a neighbourhood of one row and ``window`` samples
        either side, and ``scale``, the slides' measured spread (robust standard deviation
        of the first slide's whole screen, within 0.2 % of the map's: the slides of a
        scan differ only in which noise samples line up, so their spread is the scan's,
        and one measurement of ~10^5 values, to about 0.5 %, sets every slide's
        threshold alike)."""
        shifts = self.term_shifts(offsets)
        acc = self.screen_sums(shifts)
        if self.scale is None:   # a slide's spread is the scan's: measured on the first
            coarse = self.normalized(acc)
            self.scale = measured_scale(coarse, coarse.size)
        scale = self.scale
        threshold = floor * scale
        # in time order: a peak's positions share detector samples
        fr, fc = _above(acc, (REFINE * threshold * self.coarse_levels).astype(np.float32))
        if len(fr) * 3 * (2 * self.step + 1) > MAX_REFINED * self.z.size:
            z = self.full_map(shifts)
            r, s = local_maxima(z, threshold, self.window)
            return r, s, z[r, s], scale
        self.slide += 1          # (2^31 slides of one scan before it wraps)
        r, s = _refined_maxima(self.terms32, self.weights32, self.indptr, self.members, shifts,
                               self.norm32, fr, fc, self.step, self.window, self.z,
                               self.stamp, self.slide, np.float32(threshold))
        return r, s, self.z[r, s], scale

    def full_map(self, shifts):
        """The slide's whole map (unnormalized Z, float32 sums) from the terms' ``shifts``."""
        acc = np.zeros(self.z.shape, np.float32)
        used = np.flatnonzero(np.any(self.term_weights != 0, axis=0))
        shift_add(self.terms, self.weights32, used, shifts, acc)
        with np.errstate(invalid="ignore", divide="ignore"):
            return acc / self.norm32[:, None]

    def largest_share(self, rows, samples, offsets):
        """:func:`so_transients.coherent.statistic.largest_share` of the slide ``offsets``'s map at
        (``rows``, ``samples``): of its detectors, also when the slide moves groups."""
        shifts = self.lags + np.asarray(offsets, np.int64)
        return term_shares(self.snr, self.weights, self.detector_members, shifts, rows,
                           samples)

    def coarse_map(self, shifts):
        """The screen: Z on every other row and every ``step``-th sample (both from 0),
        from the terms' cyclic ``shifts`` (samples, in [0, nsamp))."""
        return self.normalized(self.screen_sums(shifts))

    def screen_sums(self, shifts):
        """The screen's sums before normalization (a buffer the next slide re-uses)."""
        if self._screen is None:
            self._screen = np.empty((len(self.coarse_weights), self.phases.shape[2]),
                                    np.float32)
        acc = self._screen
        acc[:] = 0.0
        _coarse_shift_add(self.phases, self.snr.shape[1], self.coarse_weights,
                          self.coarse_used, np.asarray(shifts)[self.screen_terms], acc)
        return acc

    def normalized(self, acc):
        """Screen sums ``acc`` in units of Z (NaN on rows without detectors)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return acc / self.coarse_norm[:, None]


@njit(cache=True, nogil=True)
def sample_phases(snr, step, quantum, which):
    """``(step, len(which), ceil(nsamp / step))`` int16: ``out[p, k, j] = snr[which[k], j *
    step + p] / quantum[k]`` rounded (0 past the end), so that every ``step``-th sample from
    any start is contiguous; beyond +-32767 quanta clipped."""
    nsamp = snr.shape[1]
    out = np.zeros((step, len(which), -(-nsamp // step)), np.int16)
    for k in range(len(which)):
        src, scale = snr[which[k]], 1.0 / quantum[k]
        for j in range(out.shape[2]):
            for p in range(min(step, nsamp - j * step)):
                v = src[j * step + p] * scale
                out[p, k, j] = np.rint(min(max(v, -32767.0), 32767.0))
    return out


def term_quanta(terms, which, n_values=1024) -> np.ndarray:
    """(len(which),) the 16-bit screen's unit for each of the partial maps ``which``:
    1/256 of its robust spread (from ``n_values`` evenly spaced samples, to about 5 %): a
    partial map rounded to it is within 0.001 of its spread over a group; a value clipped
    at 128 spreads (a glitch's) still makes its position's screen value far above any
    threshold. 1 for a map of zeros."""
    every = max(1, terms.shape[1] // n_values)
    spread = 1.4826 * np.median(np.abs(terms[which, ::every]), axis=1)
    return np.where(spread > 0, spread / 256.0, 1.0)


@njit(cache=True, nogil=True)
def _above(coarse, levels):
    """``(rows, cols)`` of the screen's positions at least their row's ``levels``, column
    by column (scanned row by row, 64 columns at a time, a block looked into only when it
    holds one: the few found are then put in column order)."""
    nrow, ncol = coarse.shape
    rows, cols = np.empty(nrow * ncol, np.int64), np.empty(nrow * ncol, np.int64)
    k = 0
    for r in range(nrow):
        level, row = levels[r], coarse[r]
        for lo in range(0, ncol, 64):
            hi = min(lo + 64, ncol)
            n = 0
            for j in range(lo, hi):           # (branch-free: vectorized)
                n += row[j] >= level
            if n == 0:
                continue
            for j in range(lo, hi):
                if row[j] >= level:
                    rows[k], cols[k] = r, j
                    k += 1
    order = np.argsort(cols[:k] * nrow + rows[:k])
    return rows[:k][order], cols[:k][order]


@njit(cache=True, nogil=True)
def _coarse_shift_add(phases, nsamp, weights, used, shifts, acc):
    """``acc[r, j] += weights[r, d] * snr[d, (j * step + shifts[d]) % nsamp]`` from the
    ``phases`` of ``snr`` (:func:`sample_phases`)."""
    step = phases.shape[0]
    nrow, ncol = acc.shape
    for k in range(len(used)):
        d = used[k]
        s = shifts[d]
        wrap = min(ncol, (nsamp - s + step - 1) // step)   # first column whose index wraps
        late = s - nsamp                                   # its index: j * step + late
        p_late = late % step
        for r in range(nrow):
            w = weights[r, d]
            if w != 0.0:
                add_slice(acc[r], phases[s % step, d], w, 0, wrap, s // step)
                add_slice(acc[r], phases[p_late, d], w, wrap, ncol, (late - p_late) // step)


@njit(cache=True, nogil=True)
def _refined_maxima(snr, weights, indptr, members, shifts, norm, rows, cols, step, window,
                    z, stamp, slide, threshold):
    """``(rows, samples)`` of the local maxima at least ``threshold`` within one row and
    ``step`` samples of the coarse positions (``rows``, ``cols``: every other row, every
    ``step``-th sample), no position within one row and ``window`` samples higher (as
    :func:`so_transients.coherent.statistic.local_maxima`). ``z`` is summed where it is needed:
    there ``stamp`` is set to ``slide``."""
    nrow, nsamp = z.shape
    # the cores, merged into runs row by row, then summed run by run
    run_rows, run_lo, run_hi = _core_runs(rows, cols, step, nrow, nsamp)
    for k in range(len(run_rows)):
        _sum_span(snr, weights, indptr, members, shifts, norm, z, stamp, slide, run_rows[k],
                  run_lo[k], run_hi[k])
    out_rows, out_samples = [], []
    for k in range(len(rows)):
        r, t = 2 * rows[k], cols[k] * step
        for rr in range(max(r - 1, 0), min(r + 2, nrow)):
            for tt in range(max(t - step, 0), min(t + step + 1, nsamp)):
                if z[rr, tt] < threshold or stamp[rr, tt] != slide:
                    continue
                stamp[rr, tt] = -slide        # tested (its value is kept)
                for r2 in range(max(rr - 1, 0), min(rr + 2, nrow)):
                    _sum_span(snr, weights, indptr, members, shifts, norm, z, stamp, slide,
                              r2, max(tt - window, 0), min(tt + window + 1, nsamp))
                if is_top(z, rr, tt, window):
                    out_rows.append(rr)
                    out_samples.append(tt)
    return np.array(out_rows, np.int64), np.array(out_samples, np.int64)


@njit(cache=True, nogil=True)
def _core_runs(rows, cols, step, nrow, nsamp):
    """``(rows, lo, hi)``: the fine rows and sample spans within one row and ``step``
    samples of the coarse positions (``rows``, ``cols``), overlapping spans of a row merged,
    in order of ``lo``."""
    n = 3 * len(rows)
    r_all, lo_all, hi_all = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
    m = 0
    for k in range(len(rows)):
        r, t = 2 * rows[k], cols[k] * step
        for rr in range(max(r - 1, 0), min(r + 2, nrow)):
            r_all[m], lo_all[m], hi_all[m] = rr, max(t - step, 0), min(t + step + 1, nsamp)
            m += 1
    order = np.argsort(r_all[:m] * (nsamp + 1) + lo_all[:m])
    out_r, out_lo, out_hi = np.empty(m, np.int64), np.empty(m, np.int64), np.empty(m, np.int64)
    j = -1
    for i in order:
        if j >= 0 and r_all[i] == out_r[j] and lo_all[i] <= out_hi[j]:
            out_hi[j] = max(out_hi[j], hi_all[i])
        else:
            j += 1
            out_r[j], out_lo[j], out_hi[j] = r_all[i], lo_all[i], hi_all[i]
    # in time order: the runs of a peak's neighbouring rows read the same detector samples
    # while they are in cache
    order = np.argsort(out_lo[:j + 1])
    return out_r[order], out_lo[order], out_hi[order]


@njit(cache=True, nogil=True, inline="always")
def _sum_span(snr, weights, indptr, members, shifts, norm, z, stamp, slide, r, lo, hi):
    """``z[r, lo:hi]``: the normalized sum over row ``r``'s detectors where it is not yet
    summed in this ``slide`` (``stamp`` not +-``slide``), run by run."""
    nsamp = z.shape[1]
    zr = z[r]
    t = lo
    while t < hi:
        if abs(stamp[r, t]) == slide:
            t += 1
            continue
        end = t
        while end < hi and abs(stamp[r, end]) != slide:
            stamp[r, end] = slide
            zr[end] = 0.0
            end += 1
        for i in range(indptr[r], indptr[r + 1]):
            d = members[i]
            w, s, src = weights[r, d], shifts[d], snr[d]
            wrap = max(t, min(end, nsamp - s))
            for u in range(t, wrap):
                zr[u] += w * src[u + s]
            for u in range(wrap, end):
                zr[u] += w * src[u + s - nsamp]
        for u in range(t, end):
            zr[u] /= norm[r]
        t = end
