"""The maxima of a coherent map that look like a source crossing: glitch vetoes.

A local maximum of Z (:mod:`so_transients.coherent`) is kept when it is the strongest of
its neighbours (within two beam sigmas across and three beam-crossing times along) and no
glitch veto removes it:

- ``max_single_share``: one detector makes more than this share of the maximum's sum (a
  glitch or cosmic ray on one detector);
- ``max_instant_share``: more than this share of its positive sum comes from detectors the
  position crosses within :data:`INSTANT` beam-crossing times (beam sigma / drift speed:
  the width of the filtered response to a glitch) of each other, i.e. from one instant (a
  glitch or readout jump on many detectors at once; a source's sum is spread over the
  whole crossing).

``transient_find``'s coherent mode selects its candidates and sweep-stacking seeds so, and
``transient_significance`` the sign-inverted data's seeds, so that the stacks' background
is selected as the data's stacks are.
"""
from __future__ import annotations

import numpy as np

from .coherent import local_maxima


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


def vetoed(snr, geometry, weights, beam_sigma, peak_rows, peak_samples, cfg, sign=1.0):
    """For each map position (``peak_rows`` indices, ``peak_samples``), whether a glitch
    veto removes it: one detector makes more than ``cfg.max_single_share`` of its sum, or
    detectors crossed at one instant more than ``cfg.max_instant_share`` of it
    (``weights``: the map's, :func:`so_transients.coherent.row_weights`; ``sign=-1``: of
    the sign-inverted ``snr``'s map)."""
    lags = geometry.lag_samples
    window = INSTANT * geometry.crossing_samples(beam_sigma)
    out = np.zeros(len(peak_rows), bool)
    for k, (r, t0) in enumerate(zip(peak_rows, peak_samples)):
        dets, _, terms = sum_terms(snr, weights, lags, r, t0)
        single, instant = shares(sign * terms, lags[dets], window)
        out[k] = single > cfg.max_single_share or instant > cfg.max_instant_share
    return out


def peaks(snr, geometry, z, weights, beam_sigma, threshold, cfg, sign=1.0):
    """``(rows, samples)`` indices of the maxima of ``z`` (the map of ``sign`` x ``snr``) at
    least ``threshold``, the strongest of neighbours, that no glitch veto removes
    (``cfg``: ``row_step``, ``max_single_share``, ``max_instant_share``)."""
    window = geometry.crossing_samples(beam_sigma)
    r, s = local_maxima(z, threshold, window)
    keep = suppress_neighbours(z[r, s], r, s, int(np.ceil(2.0 / cfg.row_step)), 3 * window)
    r, s = r[keep], s[keep]
    keep = ~vetoed(snr, geometry, weights, beam_sigma, r, s, cfg, sign)
    return r[keep], s[keep]
