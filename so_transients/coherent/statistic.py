"""The coherent detection statistic of one wafer crossing (issue: significance you can trust).

A source at sky position ``p`` crosses a wafer along the scan: detector ``d`` sees it when the
source's drift across the focal plane brings it level with the detector along the scan, at
``t_d = t0 + along_d / speed``, at a cross-scan offset ``delta_d = across_d - c``. With ``A_d``
the matched-filter amplitude of detector ``d`` (S/N x sigma_d), the maximum-likelihood
estimate of a steady source's flux over the crossing and its S/N are

    S(p) = sum_d (b_d / sigma_d^2) A_d(t_d) / sum_d b_d^2 / sigma_d^2
    Z(p) = sum_d (b_d / sigma_d) snr_d(t_d) / sqrt(sum_d b_d^2 / sigma_d^2),  b_d = B(delta_d)

(``B`` the Gaussian beam across the scan). Positions are laid out as ``(c, t0)``: rows of
cross-scan offset ``c`` from the wafer's centre, ``row_step`` beam sigmas apart (a source
midway between rows loses ``1 - exp(-(row_step / 4)^2)`` of its Z: 4 % at the default 0.8),
and every sample ``t0`` at which the position passes the centre. :func:`coherent_map` is a
shift-and-add of the detectors' S/N streams. Its noise is not unit: detectors share
residual atmosphere. :func:`measured_scale` measures it on the map itself (robust standard
deviation), as ``transient_filter`` measures its S/N normalization.

Everything here is on arrays: focal-plane offsets (radians), S/N streams, per-detector
amplitude noise (mJy); no AxisManager.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from so_transients.common import pointing
from so_transients.common.robust import mad_std
from so_transients.common.scan_geometry import drift_velocity


@dataclass
class CrossingGeometry:
    """The drift of sky positions across the focal plane during one constant-speed scan."""

    along: np.ndarray        # (ndet,) offset of each detector along the drift, rad
    across: np.ndarray       # (ndet,) offset across it, rad
    speed: float             # rad/s of the drift
    sample_rate: float       # Hz
    centre: tuple = (0.0, 0.0)        # (xi, eta) the offsets are from
    direction: tuple = (1.0, 0.0)     # unit vector of the drift in (xi, eta)

    @classmethod
    def from_drift(cls, xi, eta, velocity, sample_rate, centre=None):
        """From detector positions and the drift ``velocity`` (rad/s, (2,)) of a sky position
        across the focal plane; offsets from ``centre`` (default: the detectors' median)."""
        xi, eta = np.asarray(xi, float), np.asarray(eta, float)
        centre = (np.median(xi), np.median(eta)) if centre is None else centre
        speed = float(np.hypot(*velocity))
        ux, uy = np.asarray(velocity, float) / speed
        out = cls(np.zeros(0), np.zeros(0), speed, float(sample_rate),
                  (float(centre[0]), float(centre[1])), (float(ux), float(uy)))
        out.along, out.across = out.point_offsets(xi, eta)
        return out

    def point_offsets(self, xi, eta):
        """Along- and across-drift offsets (rad) of focal-plane points from the centre."""
        (ux, uy), (x0, y0) = self.direction, self.centre
        dx, dy = np.asarray(xi, float) - x0, np.asarray(eta, float) - y0
        return dx * ux + dy * uy, -dx * uy + dy * ux

    def crossing_samples(self, beam_sigma) -> int:
        """Samples a position takes to drift one beam sigma (at least 1): the time unit of
        every neighbourhood on the map (local maxima, glitch instants, candidate windows)."""
        return max(1, int(round(self.sample_rate * beam_sigma / self.speed)))

    @property
    def lag_samples(self) -> np.ndarray:
        """Each detector's delay (samples, rounded) after the centre for a passing source."""
        return np.rint(self.along / self.speed * self.sample_rate).astype(int)


def crossing_geometry(timestamps, bore_q, xi, eta, samples, sample_rate):
    """The drift across the detectors ``xi``, ``eta`` during the scan ``samples``, measured
    for the sky position at the detectors' centre at the scan's middle sample."""
    mid = int(samples[len(samples) // 2])
    centre = (float(np.median(xi)), float(np.median(eta)))
    ra, dec = pointing.radec_of_samples(bore_q, [centre[0]], [centre[1]], [0], [mid])
    velocity = drift_velocity(timestamps, bore_q, ra, dec, [timestamps[mid]])[0]
    return CrossingGeometry.from_drift(xi, eta, velocity, sample_rate, centre)


def row_offsets(geometry: CrossingGeometry, beam_sigma, row_step):
    """Cross-scan offsets (rad) of the rows of positions: ``row_step`` beam sigmas apart,
    covering the detectors' cross-scan extent."""
    lo, hi = np.min(geometry.across), np.max(geometry.across)
    step = row_step * beam_sigma
    n = int(np.ceil((hi - lo) / step)) + 1
    return lo + step * np.arange(n) - 0.5 * (step * (n - 1) - (hi - lo))


def row_weights(geometry: CrossingGeometry, rows, beam_sigma, sigma_amp, live, reach=3.0):
    """(nrow, ndet) weights ``b_d / sigma_d`` of each detector in each row (0 beyond
    ``reach`` beam sigmas and for dead detectors) and (nrow,) the norms
    ``sqrt(sum_d b_d^2 / sigma_d^2)``."""
    delta = geometry.across[None, :] - np.asarray(rows)[:, None]
    beam = np.exp(-0.5 * (delta / beam_sigma) ** 2) * (np.abs(delta) <= reach * beam_sigma)
    sigma = np.asarray(sigma_amp, float)
    ok = np.asarray(live, bool) & (sigma > 0)
    weights = np.where(ok[None, :], beam / np.where(ok, sigma, 1.0)[None, :], 0.0)
    return weights, np.sqrt(np.sum(weights**2, axis=1))


def coherent_map(snr, geometry: CrossingGeometry, rows, beam_sigma, sigma_amp, live,
                 offsets=None, with_flux=True, finite=False, dtype=np.float64):
    """``(z, flux)``: Z and the flux estimate S (mJy) on rows x samples of ``snr`` (ndet,
    nsamp), with rows of cross-scan offsets ``rows``. Positions whose crossing reaches past
    either end of ``snr`` sum the detectors crossed inside it (:func:`fill_edges`).
    ``offsets`` (ndet,) samples added to each detector's lag (a time slide, applied
    cyclically). ``with_flux=False``: Z only (``flux`` is None);
    ``finite``: ``snr`` is known to hold no NaN (a caller making many maps of it cleans it
    once, :func:`finite_snr`); ``dtype``: of the sums (float32 for the many maps of a
    background: 1.6-3x faster, Z to 1e-6)."""
    snr = np.asarray(snr) if finite else finite_snr(snr)   # NaN samples add nothing
    nsamp = snr.shape[1]
    weights, norm = row_weights(geometry, rows, beam_sigma, sigma_amp, live)
    lags = geometry.lag_samples
    shifts = lags if offsets is None else lags + np.asarray(offsets, np.int64)
    acc = np.zeros((len(rows), nsamp), dtype)
    used = np.flatnonzero(np.any(weights != 0, axis=0))
    shift_add(snr, np.ascontiguousarray(weights, dtype), used, shifts.astype(np.int64), acc)
    norm = norm.astype(dtype)
    with np.errstate(invalid="ignore", divide="ignore"):
        flux = acc / (norm**2)[:, None] if with_flux else None
        acc /= norm[:, None]
    z = acc
    if offsets is None:      # positions whose crossing wraps around the ends: no wrapping
        fill_edges(z, snr, weights, norm, lags, flux)
    return z, flux


#: A position at a scan end is on the map when the detectors crossed inside the scan hold
#: at least this fraction of its row's weight^2 (a source crossing the wafer's centre at the
#: scan's first or last sample: about half).
EDGE_FRACTION = 0.4


def interior(nsamp, lags) -> slice:
    """The samples of a map whose whole crossing, delayed by the detectors' ``lags``, lies
    within ``nsamp`` samples."""
    lo = min(max(0, -int(np.min(lags))), nsamp)
    return slice(lo, max(nsamp - max(0, int(np.max(lags))), lo))


def edge_samples(nsamp, lags) -> np.ndarray:
    """The samples of a map whose crossing reaches past either end (:func:`interior`'s
    complement)."""
    inner = interior(nsamp, lags)
    return np.r_[0:inner.start, inner.stop:nsamp]


def fill_edges(z, snr, weights, norm, lags, flux=None):
    """``z`` (rows x samples of a map: cyclic sums / ``norm``) with the positions whose
    crossing reaches past either end of ``snr`` (finite) summed over the detectors crossed
    inside it, ``sum_d w_d snr_d / sqrt(sum_d w_d^2)`` over them (``flux``: the sum over
    ``sum_d w_d^2``), and NaN where those hold less than :data:`EDGE_FRACTION` of the row's
    weight^2 (in place; returned). A source crossing as a scan starts or ends is searched
    with the detectors that saw it."""
    nsamp = z.shape[1]
    t = edge_samples(nsamp, lags)
    used = np.flatnonzero(np.any(weights != 0, axis=0))
    if not len(t) or not len(used):
        return z
    at = t[:, None] + np.asarray(lags)[None, used]
    inside = (at >= 0) & (at < nsamp)
    values = np.where(inside, np.asarray(snr)[used[None, :], np.clip(at, 0, nsamp - 1)], 0.0)
    w = np.asarray(weights, float)[:, used]
    sums, norm2 = values @ w.T, inside.astype(float) @ (w**2).T
    with np.errstate(invalid="ignore", divide="ignore"):
        kept = norm2 >= EDGE_FRACTION * np.asarray(norm, float)[None, :] ** 2
        z[:, t] = np.where(kept, sums / np.sqrt(norm2), np.nan).T
        if flux is not None:
            flux[:, t] = np.where(kept, sums / norm2, np.nan).T
    return z


def finite_snr(snr):
    """``snr`` as an array with NaN (dead or cut samples) replaced by 0 (no copy when it has
    none)."""
    snr = np.asarray(snr)
    return snr if np.isfinite(snr).all() else np.nan_to_num(snr)


#: Samples of the map summed at a time: every row's block of the accumulator (50 rows x 4096
#: x 8 bytes) stays in cache while all detectors are added to it.
SHIFT_ADD_BLOCK = 4096


@njit(cache=True, nogil=True)
def shift_add(snr, weights, used, shifts, acc):
    """``acc[r, t] += weights[r, d] * snr[d, (t + shifts[d]) % nsamp]`` over the detectors
    ``used`` and the rows where their weight is not 0 (``snr`` finite)."""
    nrow, nsamp = acc.shape
    first, last = _weighted_rows(weights, used)
    # block by block in time, so that the accumulator's rows are read from cache (2-4x
    # faster than a whole row per detector); each sum still adds the detectors in order
    for t0 in range(0, nsamp, SHIFT_ADD_BLOCK):
        t1 = min(t0 + SHIFT_ADD_BLOCK, nsamp)
        for k in range(len(used)):
            d = used[k]
            s = shifts[d] % nsamp
            wrap = max(t0, nsamp - s)        # from here the source index wraps around
            for r in range(first[k], last[k] + 1):
                w = weights[r, d]
                if w != 0.0:
                    add_slice(acc[r], snr[d], w, t0, min(t1, wrap), s)
                    add_slice(acc[r], snr[d], w, wrap, t1, s - nsamp)


@njit(cache=True, nogil=True, inline="always")
def add_slice(row, src, w, lo, hi, shift):
    """``row[lo:hi] += w * src[lo + shift:hi + shift]`` as a plain loop over two slices
    (which the compiler vectorizes)."""
    if hi <= lo:
        return
    head, tail = row[lo:hi], src[lo + shift:hi + shift]
    for t in range(hi - lo):
        head[t] += w * tail[t]


@njit(cache=True, nogil=True)
def _weighted_rows(weights, used):
    """First and last row where each detector of ``used`` has a weight (last < first: none)."""
    nrow = weights.shape[0]
    first = np.full(len(used), nrow, np.int64)
    last = np.full(len(used), -1, np.int64)
    for k in range(len(used)):
        for r in range(nrow):
            if weights[r, used[k]] != 0.0:
                first[k] = min(first[k], r)
                last[k] = r
    return first, last


def largest_share(snr, geometry: CrossingGeometry, rows, beam_sigma, sigma_amp, live,
                  peak_rows, peak_samples, offsets=None, sign=1.0):
    """For each map position (``peak_rows``, ``peak_samples``) the largest share one
    detector has of its Z's sum: near 1 when a single detector's spike makes the peak (a
    glitch, or a bright source's own detectors moved apart by a time slide), small for a
    source or noise spread over the many detectors of a crossing (1 where the sum is not
    positive). ``sign=-1``: of the sign-inverted ``snr``'s map."""
    weights, _ = row_weights(geometry, rows, beam_sigma, sigma_amp, live)
    shifts = geometry.lag_samples + (0 if offsets is None else np.asarray(offsets, np.int64))
    return term_shares(snr, weights, row_members(weights), shifts, peak_rows, peak_samples,
                       sign, cyclic=offsets is not None)


def term_shares(snr, weights, members, shifts, rows, samples, sign=1.0, cyclic=True):
    """The largest term's share ``best / total`` of each position's sum, from
    :func:`point_sums` (``members``: its ``(indptr, members)``), 1 where the sum is not
    positive."""
    total, best = point_sums(snr, weights, *members, shifts, rows, samples, sign, cyclic)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, best / total, 1.0)


def row_members(weights):
    """``(indptr, members)``: the detectors with a weight in row ``r`` are
    ``members[indptr[r]:indptr[r + 1]]`` (ascending)."""
    r, d = np.nonzero(weights)
    return (np.searchsorted(r, np.arange(weights.shape[0] + 1)).astype(np.int64),
            d.astype(np.int64))


def point_sums(snr, weights, indptr, members, shifts, rows, samples, sign=1.0, cyclic=True):
    """``(total, best)`` at each map position (``rows``, ``samples``): the sum of its terms
    ``sign * weights[r, d] * snr[d, (t + shifts[d]) % nsamp]`` (NaN samples: 0; without
    ``cyclic``, only the samples inside ``snr``), its unnormalized Z, and the largest term
    (at least 0); ``indptr``, ``members``: :func:`row_members` of ``weights``."""
    n = len(rows)
    total, best = np.zeros(n), np.zeros(n)
    _point_sums(np.asarray(snr), np.ascontiguousarray(weights), indptr, members,
                np.asarray(shifts, np.int64), np.asarray(rows, np.int64),
                np.asarray(samples, np.int64), float(sign), bool(cyclic), total, best)
    return total, best


@njit(cache=True, nogil=True)
def _point_sums(snr, weights, indptr, members, shifts, rows, samples, sign, cyclic, total,
                best):
    nsamp = snr.shape[1]
    for k in range(len(rows)):
        r, t = rows[k], samples[k]
        tot, top = 0.0, 0.0
        for i in range(indptr[r], indptr[r + 1]):
            d = members[i]
            if not cyclic and not 0 <= t + shifts[d] < nsamp:
                continue
            v = snr[d, (t + shifts[d]) % nsamp]
            if np.isfinite(v):
                term = sign * weights[r, d] * v
                tot += term
                top = max(top, term)
        total[k] = tot
        best[k] = top


MAX_SCALE_VALUES = 20_000


def measured_scale(z, max_values=MAX_SCALE_VALUES, lags=None) -> float:
    """The robust standard deviation of a map's finite values (1 for independent noise),
    from at most about ``max_values`` of them, evenly spread; with the detectors' ``lags``,
    of the positions whose whole crossing is in the scan only (at the scan ends fewer
    detectors make the sum, :func:`fill_edges`, which shares less of their correlation)."""
    if lags is not None:
        z = np.asarray(z)[:, interior(np.shape(z)[1], lags)]
    values = np.asarray(z)[np.isfinite(z)]
    # 20,000 values give it to about 1 % (robust std); a scan's map has 10^5 or more
    values = values[::max(1, len(values) // max_values)]
    scale = float(mad_std(values)) if len(values) > 10 else 1.0
    return scale if scale > 0 else 1.0      # a map of zeros (no live samples): Z 0


def local_maxima(z, threshold, time_window):
    """``(row, sample)`` of the local maxima of ``z`` at least ``threshold``, in a
    neighbourhood of one row either side and ``time_window`` samples either side (NaN is
    never a maximum and does not hide one)."""
    rows, samples = np.nonzero(np.asarray(z) >= threshold)
    keep = _is_local_max(np.ascontiguousarray(z), rows, samples, int(time_window))
    return rows[keep], samples[keep]


@njit(cache=True, nogil=True)
def _is_local_max(z, rows, samples, half):
    out = np.ones(len(rows), np.bool_)
    for k in range(len(rows)):
        out[k] = is_top(z, rows[k], samples[k], half)
    return out


@njit(cache=True, nogil=True, inline="always")
def is_top(z, r, t, half):
    """Whether no position within one row and ``half`` samples of (r, t) is higher."""
    nrow, nsamp = z.shape
    v = z[r, t]
    for rr in range(max(r - 1, 0), min(r + 2, nrow)):
        for tt in range(max(t - half, 0), min(t + half + 1, nsamp)):
            if z[rr, tt] > v:
                return False
    return True


def window_max(z, rows, samples, half_rows, half_samples):
    """The highest finite value of ``z`` within ``half_rows`` rows and ``half_samples``
    samples of each position (``rows``, ``samples``) (-inf where there is none)."""
    out = np.full(len(rows), -np.inf)
    _window_max(np.ascontiguousarray(z), np.asarray(rows, np.int64),
                np.asarray(samples, np.int64), int(half_rows), int(half_samples), out)
    return out


@njit(cache=True, nogil=True)
def _window_max(z, rows, samples, half_rows, half_samples, out):
    nrow, nsamp = z.shape
    for k in range(len(rows)):
        r, t = rows[k], samples[k]
        for rr in range(max(r - half_rows, 0), min(r + half_rows + 1, nrow)):
            for tt in range(max(t - half_samples, 0), min(t + half_samples + 1, nsamp)):
                if z[rr, tt] > out[k]:          # False for NaN
                    out[k] = z[rr, tt]


def time_slide_offsets(ndet, nsamp, min_shift, rng, n_slides=None):
    """Random cyclic offsets (samples) per detector, each at least ``min_shift`` from 0
    modulo ``nsamp``: a real source no longer lines up across detectors, while each
    detector's noise and glitches keep their statistics. (ndet,), or (n_slides, ndet) for
    that many slides at once."""
    if nsamp <= 2 * min_shift:
        raise ValueError(f"a scan of {nsamp} samples is too short for time slides of at "
                         f"least {min_shift} samples")
    size = ndet if n_slides is None else (n_slides, ndet)
    return rng.integers(min_shift, nsamp - min_shift, size=size)


def false_alarm_rate(statistics, background, live_time_hours):
    """False alarms per hour (of the background's wafer-band) with a statistic at least as
    large as each of ``statistics``, from the ``background`` peaks found in
    ``live_time_hours``; a statistic above every background peak gets the bound
    ``1 / live_time_hours`` halved (no count: at most about one in the live time)."""
    background = np.sort(np.asarray(background, float))
    stats = np.atleast_1d(np.asarray(statistics, float))
    count = len(background) - np.searchsorted(background, stats, side="left")
    return np.where(count > 0, count, 0.5) / live_time_hours
