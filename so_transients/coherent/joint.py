"""Both bands of a dichroic wafer searched together: the joint-band statistic J.

Every MF wafer sees f090 and f150 (every UHF wafer f220 and f280) at the same moment from
nearly the same focal-plane positions. For one scan, each band's coherent map
(:func:`so_transients.coherent.statistic.coherent_map`) is made on the same positions: one
drift (the detectors of both bands: one centre, one velocity, :func:`joint_geometries`) and
one set of rows, ``row_step`` sigmas of the narrower beam apart (:func:`joint_rows`). Each
band's map is in units of its own measured spread, ``Z_b``, and estimates the band's flux
with inverse noise ``n_b`` per row (1/mJy). A source of spectral index ``alpha`` has
``S_b = S_0 (nu_b / nu_0)^alpha``, so the maximum-likelihood S/N of ``S_0`` is

    J_alpha = m^T C^-1 Z / sqrt(m^T C^-1 m),   m_b = (nu_b / nu_0)^alpha n_b

with ``C`` the correlation of the bands' maps (both bands see the same residual atmosphere:
0.22-0.32 between f090 and f150, measured on each scan's maps, :func:`band_correlation`;
ignoring it widens J's noise by sqrt(1 + rho) and erases the gain), and ``J`` is the
highest ``J_alpha`` over a few indices (:data:`DEFAULT_INDICES`, -1 to +3:
synchrotron-like to dust-like). For equal per-band significance the gain over either band
alone is up to sqrt(2 / (1 + rho)); a source one band cannot see keeps that band's weight small at an
index that favours the other. The trials the maximum over indices adds are counted by the
background, which ranks ``J`` among the same statistic made of time slides and of the
sign-inverted data (:mod:`so_transients.significance.joint_far`).

``nu`` are the bands' centre frequencies (:data:`so_transients.common.bands.CENTER_GHZ`),
``nu_0`` the first band's. Everything here is on arrays; no AxisManager.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from so_transients.common.bands import CENTER_GHZ
from so_transients.coherent.statistic import (
    MAX_SCALE_VALUES, CrossingGeometry, coherent_map, crossing_geometry, local_maxima,
    measured_scale, point_sums, row_members, row_weights
)
from so_transients.coherent.vetoes import INSTANT, shares, sum_terms
from so_transients.common.robust import mad_std
from so_transients.common.scan_geometry import sample_rate as rate_of

#: Spectral indices the joint statistic is maximised over (S proportional to nu^alpha).
DEFAULT_INDICES = (-1.0, 0.0, 1.0, 2.0, 3.0)


@dataclass
class BandScan:
    """One band's part of a scan: its live detectors' finite S/N over the scan's samples,
    their drift geometry (shared centre and velocity, :func:`joint_geometries`), the band's
    beam sigma (rad) and the detectors' amplitude noise (mJy)."""

    band: str
    snr: np.ndarray
    geometry: CrossingGeometry
    beam_sigma: float
    sigma_amp: np.ndarray

    @property
    def live(self) -> np.ndarray:
        return np.ones(len(self.sigma_amp), bool)

    def weights(self, rows):
        """:func:`so_transients.coherent.statistic.row_weights` on ``rows``."""
        return row_weights(self.geometry, rows, self.beam_sigma, self.sigma_amp, self.live)


@dataclass
class BandMap:
    """One band's map on the shared positions: ``z`` in units of its measured spread
    (``scale``, of the unnormalized map) and each row's inverse flux noise ``n`` (1/mJy;
    0 where no detector of the band reaches the row)."""

    z: np.ndarray
    scale: float
    n: np.ndarray


def joint_geometries(timestamps, bore_q, xi, eta, samples, sample_rate) -> list:
    """One :class:`CrossingGeometry` per band (``xi``, ``eta``: lists of the bands'
    detector offsets, rad) for the scan ``samples``, all with the drift measured at the
    centre of every band's detectors (:func:`so_transients.coherent.statistic.crossing_geometry`),
    so that a position is the same sky point in each."""
    common = crossing_geometry(timestamps, bore_q, np.concatenate(xi), np.concatenate(eta),
                               samples, sample_rate)
    velocity = common.speed * np.asarray(common.direction)
    return [CrossingGeometry.from_drift(x, e, velocity, sample_rate, common.centre)
            for x, e in zip(xi, eta)]


def joint_rows(scans, row_step) -> np.ndarray:
    """Cross-scan offsets (rad) of rows ``row_step`` sigmas of the narrowest beam apart,
    covering every band's detectors."""
    across = np.concatenate([s.geometry.across for s in scans])
    lo, hi = float(np.min(across)), float(np.max(across))
    step = row_step * min(s.beam_sigma for s in scans)
    n = int(np.ceil((hi - lo) / step)) + 1
    return lo + step * np.arange(n) - 0.5 * (step * (n - 1) - (hi - lo))


def band_map(scan: BandScan, rows, z=None) -> BandMap:
    """The band's :class:`BandMap` on ``rows``; ``z``: its unnormalized map when already
    made (e.g. cyclic sums with the edges filled)."""
    if z is None:
        z, _ = coherent_map(scan.snr, scan.geometry, rows, scan.beam_sigma, scan.sigma_amp,
                            scan.live, with_flux=False, finite=True)
    scale = measured_scale(z, lags=scan.geometry.lag_samples)
    _, norm = scan.weights(rows)
    return BandMap(z / scale, scale, norm / scale)


def band_correlation(z, max_values=MAX_SCALE_VALUES) -> np.ndarray:
    """(n_band, n_band) correlation of the bands' unit-spread maps ``z`` ((n_band, n_row,
    n_samp)) where all are finite, each pair's robustly from the spreads of its sum and
    difference, ``(s+^2 - s-^2) / (s+^2 + s-^2)``, on at most about ``max_values`` positions
    evenly spread. Both bands of a wafer see the same residual atmosphere: 0.22-0.32 on a
    simulated f090 and f150 hour."""
    z = np.asarray(z)
    ok = np.all(np.isfinite(z), axis=0)
    values = z[:, ok]
    values = values[:, ::max(1, values.shape[1] // max_values)]
    nband = z.shape[0]
    out = np.eye(nband)
    if values.shape[1] <= 10:
        return out
    for a in range(nband):
        for b in range(a + 1, nband):
            plus, minus = mad_std(values[a] + values[b]), mad_std(values[a] - values[b])
            total = plus**2 + minus**2
            out[a, b] = out[b, a] = (plus**2 - minus**2) / total if total > 0 else 0.0
    return out


def index_coefficients(bands, n, indices=DEFAULT_INDICES, correlation=None) -> np.ndarray:
    """``(n_index, n_band, n_row)`` coefficients of each band's unit-spread Z in
    ``J_alpha``: with ``m_b = (nu_b / nu_0)^alpha n_b`` (``n``: (n_band, n_row) inverse
    flux noise) and the bands' noise ``correlation`` (None: independent), ``C^-1 m /
    sqrt(m^T C^-1 m)``, the maximum-likelihood S/N of ``S_0`` in unit spread. A row only
    some bands reach combines those; a row none reaches: 0."""
    nu = np.array([CENTER_GHZ[b] for b in bands], float)
    ratio = (nu[None, :] / nu[0]) ** np.asarray(indices, float)[:, None]    # (nidx, nband)
    m = ratio[:, :, None] * np.asarray(n, float)[None, :, :]             # (nidx, nband, nrow)
    corr = np.eye(len(bands)) if correlation is None else np.asarray(correlation, float)
    out = np.zeros(m.shape)
    reach = np.asarray(n, float) > 0                                      # (nband, nrow)
    for pattern in np.unique(reach.T, axis=0):
        sel = np.flatnonzero(pattern)
        if not len(sel):
            continue
        rows = np.flatnonzero(np.all(reach.T == pattern, axis=1))
        inverse = np.linalg.inv(corr[np.ix_(sel, sel)])
        mm = m[:, sel][:, :, rows]                                        # (nidx, k, r)
        w = np.einsum("ij,ajr->air", inverse, mm)
        norm = np.sqrt(np.einsum("air,air->ar", mm, w))
        out[:, sel[:, None], rows[None, :]] = w / norm[:, None, :]
    return out


def map_coefficients(bands, maps, indices=DEFAULT_INDICES) -> tuple:
    """``(coefficients, correlation)``: :func:`index_coefficients` of the bands'
    :class:`BandMap` s with their measured correlation (:func:`band_correlation`)."""
    correlation = band_correlation(np.stack([m.z for m in maps]))
    return index_coefficients(bands, [m.n for m in maps], indices, correlation), correlation


def joint_map(z, coefficients):
    """``(J, best)``: the highest ``J_alpha`` at each position of the bands' unit-spread
    maps ``z`` ((n_band, n_row, n_samp)) and the index (position in the coefficients'
    first axis) that makes it; NaN (and -1) where a band reaching the row has no value."""
    z = np.ascontiguousarray(z)
    out = np.empty(z.shape[1:], np.float64)
    best = np.empty(z.shape[1:], np.int8)
    _joint(z, np.ascontiguousarray(coefficients, np.float64), out, best)
    return out, best


@njit(cache=True, nogil=True)
def _joint(z, coef, out, best):
    nband, nrow, nsamp = z.shape
    for r in range(nrow):
        for t in range(nsamp):
            out[r, t] = -np.inf
            best[r, t] = -1
        for a in range(coef.shape[0]):
            for t in range(nsamp):
                s = 0.0
                for b in range(nband):
                    c = coef[a, b, r]
                    if c != 0.0:
                        s += c * z[b, r, t]
                if s > out[r, t]:             # False for NaN
                    out[r, t] = s
                    best[r, t] = a
        for t in range(nsamp):
            if best[r, t] < 0:
                out[r, t] = np.nan


def joint_shares(scans, maps, rows, coefficients, best, peak_rows, peak_samples,
                 offsets=None, sign=1.0):
    """The largest share one detector (of any band) has of ``J``'s sum at each position
    (``peak_rows``, ``peak_samples``), at the index that makes it (``best``): near 1 for a
    glitch on one detector, small for a source spread over a crossing (1 where the sum is
    not positive). ``offsets``: per band, a time slide's per-detector offsets (cyclic);
    ``sign=-1``: of the sign-inverted data."""
    peak_rows, peak_samples = np.asarray(peak_rows), np.asarray(peak_samples)
    a = best[peak_rows, peak_samples].astype(int)
    total, top = np.zeros(len(peak_rows)), np.zeros(len(peak_rows))
    for b, (scan, m) in enumerate(zip(scans, maps)):
        weights, _ = scan.weights(rows)      # the row's norm is in term_weight
        shifts = scan.geometry.lag_samples + (0 if offsets is None else offsets[b])
        tot, big = point_sums(scan.snr, weights, *row_members(weights), shifts, peak_rows,
                              peak_samples, sign, cyclic=offsets is not None)
        k = term_weight(coefficients, m, a, b, peak_rows)
        total += k * tot
        top = np.maximum(top, k * big)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, top / total, 1.0)


def term_weight(coefficients, m: BandMap, index, band, rows):
    """What one unit of band ``band``'s unnormalized sum adds to ``J`` on ``rows`` at
    ``index``: its coefficient over the row's norm times the map's scale (``n`` x
    ``scale^2``); 0 on rows the band does not reach."""
    rows = np.asarray(rows)
    n = m.n[rows]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, coefficients[index, band, rows] / (n * m.scale**2), 0.0)


def joint_maxima(scans, maps, rows, coefficients, j, best, threshold, window,
                 max_single_share=0.5, max_instant_share=None):
    """``(rows, samples)`` of the local maxima of the joint map ``j`` at least ``threshold``
    (neighbourhood: one row and ``window`` samples either side) that no glitch veto
    removes: one detector (of any band) making more than ``max_single_share`` of J's sum,
    or, with ``max_instant_share``, detectors crossed at one instant more than that share of
    its positive sum (:func:`so_transients.coherent.vetoes.shares`: a cosmic ray hits both
    bands' detectors at once)."""
    r, s = local_maxima(j, threshold, window)
    if max_instant_share is None:
        keep = joint_shares(scans, maps, rows, coefficients, best, r, s) <= max_single_share
        return r[keep], s[keep]
    keep = np.zeros(len(r), bool)
    width = INSTANT * max(b.geometry.crossing_samples(b.beam_sigma) for b in scans)
    weights = [b.weights(rows)[0] for b in scans]
    for k, (row, sample) in enumerate(zip(r, s)):
        terms, lags = [], []
        for b, (scan, m, w) in enumerate(zip(scans, maps, weights)):
            dets, _, t = sum_terms(scan.snr, w, scan.geometry.lag_samples, row, sample)
            terms.append(t * term_weight(coefficients, m, best[row, sample], b, row))
            lags.append(scan.geometry.lag_samples[dets])
        single, instant = shares(np.concatenate(terms), np.concatenate(lags), width)
        keep[k] = single <= max_single_share and instant <= max_instant_share
    return r[keep], s[keep]


def band_scans(names, snr, rows, xi, eta, sigma_amp, beam_sigma, timestamps, bore_q, scan):
    """``(first, [BandScan, ...])`` for each scan (``scan``: scan index per sample, -1
    between scans) of the bands ``names``: band ``b``'s S/N is ``snr[b][rows[b]]`` (a
    group's whole S/N, possibly memory-mapped: one scan is read at a time, NaN as 0), its
    detectors' offsets ``xi[b]``, ``eta[b]`` (rad) and amplitude noise ``sigma_amp[b]``
    (mJy), its beam sigma ``beam_sigma[b]`` (rad)."""
    fs = rate_of(timestamps)
    for k in np.unique(scan[scan >= 0]):
        samples = np.flatnonzero(scan == k)
        if len(samples) < 2:
            continue
        lo, hi = int(samples[0]), int(samples[-1]) + 1
        geometries = joint_geometries(timestamps, bore_q, xi, eta, samples, fs)
        yield lo, [BandScan(b, np.nan_to_num(np.asarray(s[r, lo:hi], float)), g, float(beam),
                            np.asarray(sig, float))
                   for b, s, r, g, beam, sig in zip(names, snr, rows, geometries, beam_sigma,
                                                    sigma_amp)]
