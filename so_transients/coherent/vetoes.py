"""The maxima of a coherent map that look like a source crossing: glitch vetoes.

A local maximum of Z (:mod:`so_transients.coherent.statistic`) is kept when it is the strongest of
its neighbours (within two beam sigmas across and three beam-crossing times along) and no
glitch veto removes it:

- ``max_single_share``: one detector makes more than this share of the maximum's sum (a
  glitch or cosmic ray on one detector);
- ``max_instant_share``: more than this share of its positive sum comes from detectors the
  position crosses within :data:`INSTANT` beam-crossing times (beam sigma / drift speed:
  the width of the filtered response to a glitch) of each other, i.e. from one instant (a
  glitch or readout jump on many detectors at once; a source's sum is spread over the
  whole crossing);
- the chi-squared test (``chi2_bins``, ``chi2_tail``, ``chi2_mismatch``,
  :mod:`so_transients.coherent.crossing_chi2`): its detectors' S/N are not in the proportions a
  source crossing gives them.

``transient_find``'s coherent mode selects its candidates and sweep-stacking seeds so, and
``transient_significance`` its background (the chi-squared test on every maximum, all
vetoes on the sign-inverted data's stack seeds), so that the background is selected as the
data's candidates are.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from so_transients.coherent.statistic import local_maxima
from so_transients.coherent.crossing_chi2 import chi2_limit, crossing_chi2, detector_groups


@dataclass(frozen=True)
class Vetoes:
    """``transient_find``'s glitch vetoes (field names: its settings; it stores them with
    its candidates, and ``transient_significance`` selects its background with them)."""

    max_single_share: float
    max_instant_share: float
    chi2_bins: int
    chi2_tail: float
    chi2_mismatch: float

    @classmethod
    def of(cls, settings):
        """From any object with these names as attributes (a ``FindConfig``)."""
        return cls(**{f.name: getattr(settings, f.name) for f in fields(cls)})

    def groups(self, weights, geometry) -> tuple:
        """:func:`so_transients.coherent.crossing_chi2.detector_groups` of a map."""
        return detector_groups(weights, geometry, int(self.chi2_bins))

    def chi2(self, snr, weights, geometry, shifts, rows, samples, sign=1.0, groups=None,
             cyclic=False):
        """:func:`so_transients.coherent.crossing_chi2.crossing_chi2` of the map positions (``groups``:
        :meth:`groups`, computed here when not given; ``cyclic``: of a time slide's map)."""
        groups = self.groups(weights, geometry) if groups is None else groups
        return crossing_chi2(snr, weights, groups, int(self.chi2_bins), shifts, rows, samples,
                             sign, cyclic)

    def consistent(self, chi2, z):
        """Whether maxima of normalized Z ``z`` with these ``chi2`` pass the chi-squared
        test (NaN chi2: pass)."""
        limit = chi2_limit(z, int(self.chi2_bins), self.chi2_tail, self.chi2_mismatch)
        return ~(np.asarray(chi2, float) > limit)


#: "One instant": within this many beam-crossing times (beam sigma / drift speed), the width
#: of the matched filter's response to a glitch, which the filter gives the template's shape.
INSTANT = 4


def suppress_neighbours(z_peaks, rows, samples, row_reach, time_reach):
    """Indices (strongest first) of the maxima not within ``row_reach`` rows and
    ``time_reach`` samples of a stronger one kept."""
    kept = []
    for k in np.argsort(-np.asarray(z_peaks), kind="stable"):
        if not any(abs(rows[k] - rows[j]) <= row_reach and abs(samples[k] - samples[j])
                   <= time_reach for j in kept):
            kept.append(k)
    return np.asarray(kept, int)


def shares(terms, lags, window):
    """``(single, instant)``: the largest share one detector has of a maximum's sum (its
    ``terms``), and the largest share of its positive sum from detectors crossed within
    ``window`` samples of one instant (``lags``: when each is crossed); both 1 (vetoed)
    without terms."""
    if not len(terms):
        return 1.0, 1.0
    total = terms.sum()
    single = terms.max() / total if total > 0 else 1.0
    positive = np.clip(terms, 0.0, None)
    if positive.sum() <= 0:
        return single, 1.0
    order = np.argsort(lags)
    lag, pos = lags[order], np.cumsum(positive[order])
    hi = np.searchsorted(lag, lag + window, side="right") - 1
    lo = np.searchsorted(lag, lag, side="left")
    strip = pos[hi] - np.r_[0.0, pos][lo]
    return float(single), float(strip.max() / positive.sum())


def sum_terms(snr, weights, lags, row, sample):
    """``(dets, samples, terms)`` of the map position (``row`` index, ``sample`` in ``snr``):
    the detectors with weight there, the samples it crosses them at (inside ``snr``) and
    their weighted S/N, whose sum is the position's unnormalized Z."""
    dets = np.flatnonzero(weights[row])
    at = sample + lags[dets]
    inside = (at >= 0) & (at < snr.shape[1])
    dets, at = dets[inside], at[inside]
    return dets, at, weights[row, dets] * np.nan_to_num(snr[dets, at])


def vetoed(snr, geometry, weights, beam_sigma, z, peak_rows, peak_samples, vetoes: Vetoes,
           sign=1.0):
    """For each map position (``peak_rows`` indices, ``peak_samples``; ``z``: its normalized
    Z), whether a glitch veto removes it: one detector makes more than
    ``max_single_share`` of its sum, detectors crossed at one instant more than
    ``max_instant_share`` of it, or it fails the chi-squared test (``weights``: the map's,
    :func:`so_transients.coherent.statistic.row_weights`; ``sign=-1``: of the sign-inverted
    ``snr``'s map)."""
    lags = geometry.lag_samples
    window = INSTANT * geometry.crossing_samples(beam_sigma)
    out = np.zeros(len(peak_rows), bool)
    for k, (r, t0) in enumerate(zip(peak_rows, peak_samples)):
        dets, _, terms = sum_terms(snr, weights, lags, r, t0)
        single, instant = shares(sign * terms, lags[dets], window)
        out[k] = single > vetoes.max_single_share or instant > vetoes.max_instant_share
    chi2 = vetoes.chi2(snr, weights, geometry, lags, peak_rows, peak_samples, sign)
    return out | ~vetoes.consistent(chi2, z)


def peaks(snr, geometry, z, weights, beam_sigma, threshold, row_step, vetoes: Vetoes,
          sign=1.0):
    """``(rows, samples)`` indices of the maxima of ``z`` (the normalized map of ``sign`` x
    ``snr``, rows ``row_step`` beam sigmas apart) at least ``threshold``, the strongest of
    neighbours, that no glitch veto removes."""
    window = geometry.crossing_samples(beam_sigma)
    r, s = local_maxima(z, threshold, window)
    keep = suppress_neighbours(z[r, s], r, s, int(np.ceil(2.0 / row_step)), 3 * window)
    r, s = r[keep], s[keep]
    keep = ~vetoed(snr, geometry, weights, beam_sigma, z[r, s], r, s, vetoes, sign)
    return r[keep], s[keep]
