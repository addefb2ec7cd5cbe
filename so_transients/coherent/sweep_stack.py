"""Sweep stacking: the coherent statistic of one sky position summed over several crossings.

A slow flare (t_r of minutes) is crossed by a wafer on several sweeps while it is bright; each
crossing alone may stay below the coherent mode's threshold. For a flux steady over the
crossings ``k`` of a window, the maximum-likelihood estimate and its S/N combine the single
crossings' (:mod:`so_transients.coherent.statistic`): with ``n_k`` the inverse flux noise of crossing
``k`` (the row's ``sqrt(sum_d b_d^2 / sigma_d^2)`` over the map's measured spread) and ``Z_k``
its normalized Z at the position,

    S = sum_k n_k^2 S_k / sum_k n_k^2,   Z = sum_k n_k Z_k / sqrt(sum_k n_k^2),
    sigma_S = 1 / sqrt(sum_k n_k^2).

``Z_k`` is read at the position (nearest row, the sample it passes the wafer's centre), not
maximized around it, so the stacked Z of noise keeps unit spread. Positions are seeds: every
scan's local maxima at least ``stack_seed`` that no glitch veto removes (a slow flare bright
enough to stack above the threshold almost always gives one of its crossings Z >= 3). Each
seed is stacked over the crossings within ``stack_window`` seconds centred on it; a stack is
kept when it reaches ``coherent_threshold``, is higher than every single crossing in it (the
single-crossing search already has the rest), and no single crossing makes more than
``stack_max_share`` of its sum (a glitch stacked with noise). Beating the best crossing
already bounds that share by 1/sqrt(N) for N crossings of equal weight (0.71 for two), so
the share matters for two or three crossings; at 0.5 no stack of two could pass. Of stacks within two beam
sigmas of each other whose windows overlap, the highest is kept.

Everything here is on arrays (maps, boresight quaternions); no AxisManager.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from types import SimpleNamespace

import numpy as np

from so_transients.common import pointing
from so_transients.common.angles import sky_separation
from so_transients.coherent.statistic import row_weights
from so_transients.coherent.vetoes import peaks


@dataclass(frozen=True)
class StackSettings:
    """``transient_find``'s sweep stacking, as ``transient_significance`` repeats it for the
    sign-inverted data (field names: ``transient_find``'s settings; it stores them with its
    candidates)."""

    stack_window: float            # s of crossings stacked
    stack_seed: float              # stacks start from single-crossing maxima this high
    stack_max_share: float         # one crossing makes at most this of a stack's sum

    @classmethod
    def of(cls, settings):
        """From any object with these names as attributes (a ``FindConfig``)."""
        return cls(**{f.name: float(getattr(settings, f.name)) for f in fields(cls)})


@dataclass
class ScanMap:
    """What stacking keeps of one scan's coherent map."""

    scan: int
    first: int                 # first sample of the scan in the group
    geometry: object           # its CrossingGeometry
    rows: np.ndarray           # cross-scan offsets of the rows, rad
    z: np.ndarray              # (nrow, nsamp) Z in units of the map's measured spread
    flux: np.ndarray           # (nrow, nsamp) flux estimate, mJy
    n: np.ndarray              # (nrow,) inverse flux noise of each row, 1/mJy
    t_lo: float                # ctime of the scan's first and last samples
    t_hi: float


@dataclass
class Crossing:
    """A position's crossing of one scan's map."""

    scan: int
    sample: int                # group sample at which it passes the wafer's centre
    row: int                   # the map's row nearest it
    z: float
    flux: float
    n: float


def sky_position(geometry, across, bore_q, sample):
    """RA, Dec (rad) of the sky position at cross-scan offset ``across`` that passes the
    wafer's centre at ``sample``."""
    (ux, uy), (x0, y0) = geometry.direction, geometry.centre
    ra, dec = pointing.radec_of_samples(bore_q, [x0 - across * uy], [y0 + across * ux], [0],
                                        [sample])
    return float(ra[0]), float(dec[0])


def map_cell(geometry, rows, first, bore_q, ra, dec, sample):
    """``(row, t0, across)`` of (ra, dec) on a scan's map (rows ``rows``, its first sample
    group sample ``first``) from where the position is in the focal plane at group sample
    ``sample``: the nearest row's index, the map sample at which it passes the wafer's
    centre (it drifts along +direction, so it passed the centre along / speed before
    ``sample``; possibly outside the map) and its cross-scan offset (rad)."""
    row, t0, across = map_cells(geometry, rows, first, bore_q, [ra], [dec], [sample])
    return int(row[0]), int(t0[0]), float(across[0])


def map_cells(geometry, rows, first, bore_q, ra, dec, samples):
    """:func:`map_cell` of many positions at once (``samples``: one group sample each):
    arrays ``(row, t0, across)``."""
    xi, eta = pointing.sources_in_focal_plane(bore_q[np.asarray(samples, np.int64)], ra, dec)
    along, across = geometry.point_offsets(xi, eta)
    t0 = (np.asarray(samples) - first
          - np.round(along / geometry.speed * geometry.sample_rate).astype(np.int64))
    return np.argmin(np.abs(rows[None, :] - across[:, None]), axis=1), t0, across


def crossing_cells(m: ScanMap, bore_q, ra, dec, row_reach):
    """``(row, t0, ok)`` of the positions (ra, dec) (arrays) on the map ``m``: the map cell
    each passes the wafer's centre in, and whether it is on the map (within ``row_reach``
    rad of a row, not reaching past a scan end)."""
    ra, dec = np.asarray(ra, float), np.asarray(dec, float)
    nsamp = m.z.shape[1]
    sample = np.full(len(ra), m.first + nsamp // 2, np.int64)
    ok = np.ones(len(ra), bool)
    for _ in range(2):         # from the scan's middle, then from the crossing found
        row, t0, across = map_cells(m.geometry, m.rows, m.first, bore_q, ra, dec, sample)
        ok &= (t0 >= 0) & (t0 < nsamp)
        t0 = np.clip(t0, 0, nsamp - 1)
        sample = m.first + t0
    ok &= np.abs(m.rows[row] - across) <= row_reach
    return row, t0, ok


def crossing_cell(m: ScanMap, bore_q, ra, dec, row_reach):
    """``(row, t0)`` of (ra, dec) on the map ``m`` (:func:`crossing_cells`), or None when
    its path misses the map."""
    row, t0, ok = crossing_cells(m, bore_q, [ra], [dec], row_reach)
    return (int(row[0]), int(t0[0])) if ok[0] else None


def crossing_of(m: ScanMap, bore_q, ra, dec, row_reach):
    """The :class:`Crossing` of (ra, dec) in the map ``m``, or None when its path misses the
    map (:func:`crossing_cell`) or the map has no value there."""
    cell = crossing_cell(m, bore_q, ra, dec, row_reach)
    if cell is None or not np.isfinite(m.z[cell]):
        return None
    row, t0 = cell
    return Crossing(m.scan, m.first + t0, row, float(m.z[row, t0]), float(m.flux[row, t0]),
                    float(m.n[row]))


def stack(crossings) -> dict:
    """``z``, ``flux``, ``flux_err`` (mJy) and ``share`` (the largest single crossing's share
    of the sum) of a steady source over ``crossings``."""
    n = np.array([c.n for c in crossings])
    z = np.array([c.z for c in crossings])
    flux = np.array([c.flux for c in crossings])
    terms = n * z
    total = terms.sum()
    share = terms.max() / total if total > 0 else 1.0
    return dict(z=float(total / np.sqrt(np.sum(n**2))),
                flux=float(np.sum(n**2 * flux) / np.sum(n**2)),
                flux_err=float(1.0 / np.sqrt(np.sum(n**2))), share=float(share))


def kept(res, crossings, cfg) -> bool:
    """Whether the stack ``res`` (:func:`stack` of ``crossings``) is a candidate: it reaches
    ``cfg.coherent_threshold``, beats each of its crossings alone, and no crossing makes more
    than ``cfg.stack_max_share`` of its sum."""
    return (res["z"] >= cfg.coherent_threshold and res["z"] > max(c.z for c in crossings)
            and res["share"] <= cfg.stack_max_share)


def stack_seeds(maps, seeds, bore_q, timestamps, beam_sigma, row_step, window_s, cfg):
    """Stacked candidates of one band: for each seed ``(scan, sample, ra, dec)`` (group
    sample), the stack over the crossings of the maps within ``window_s`` centred on it.
    Returns dicts with ``ra``, ``dec``, ``z``, ``flux``, ``flux_err``, ``share`` and
    ``crossings`` (a list of :class:`Crossing`), highest Z first, neighbours suppressed."""
    found = []
    for (_, _, ra, dec), crossings in zip(seeds, seed_crossings(
            maps, seeds, bore_q, timestamps, row_step * beam_sigma, window_s)):
        if len(crossings) < 2:
            continue
        res = stack(crossings)
        if kept(res, crossings, cfg):
            found.append(dict(ra=ra, dec=dec, crossings=crossings, **res))
    return suppress(found, timestamps, 2.0 * beam_sigma)


def seed_crossings(maps, seeds, bore_q, timestamps, row_reach, window_s) -> list:
    """For each seed ``(scan, sample, ra, dec)``, the :class:`Crossing` list of its
    position on the maps within ``window_s`` centred on it (:func:`crossing_of`, every
    map's seeds at once)."""
    out = [[] for _ in seeds]
    if not len(seeds):
        return out
    ra, dec = (np.array([s[k] for s in seeds], float) for k in (2, 3))
    t = timestamps[np.array([s[1] for s in seeds], np.int64)]
    for m in maps:
        near = np.flatnonzero((m.t_hi >= t - window_s / 2) & (m.t_lo <= t + window_s / 2))
        row, t0, ok = crossing_cells(m, bore_q, ra[near], dec[near], row_reach)
        ok &= np.isfinite(m.z[row, t0])
        for i, r, c in zip(near[ok], row[ok], t0[ok]):
            out[i].append(Crossing(m.scan, m.first + int(c), int(r), float(m.z[r, c]),
                                   float(m.flux[r, c]), float(m.n[r])))
    return out


def map_seeds(snr, m: ScanMap, beam_sigma, sigma_amp, live, bore_q, row_step,
              settings: StackSettings, vetoes, sign=1.0):
    """Seeds ``(scan, sample, ra, dec)`` of the map of ``m`` (``snr``: its scan's S/N;
    ``m.z``: the data's map; ``sign=-1``: of the sign-inverted data) as ``transient_find``
    seeds the data's stacks: its maxima from ``stack_seed``, the strongest of neighbours,
    that no glitch veto (``vetoes``, :class:`so_transients.coherent.vetoes.Vetoes`)
    removes."""
    weights, _ = row_weights(m.geometry, m.rows, beam_sigma, sigma_amp, live)
    r, s = peaks(snr, m.geometry, sign * m.z, weights, beam_sigma, settings.stack_seed,
                 row_step, vetoes, sign=sign)
    return [(m.scan, m.first + int(t), *sky_position(m.geometry, m.rows[row], bore_q,
                                                     m.first + int(t)))
            for row, t in zip(r, s)]


def inverted_stacks(maps, seeds, bore_q, timestamps, beam_sigma, row_step,
                    settings: StackSettings, floor):
    """Z of the stacks of the sign-inverted ``maps`` (every correlation between detectors
    and sweeps kept, no source) from ``floor`` up, from their ``seeds``
    (:func:`map_seeds` with ``sign=-1``) and selected as the data's are: the background of stacked
    candidates over the maps' live time."""
    flipped = [ScanMap(m.scan, m.first, m.geometry, m.rows, -m.z, -m.flux, m.n, m.t_lo,
                       m.t_hi) for m in maps]
    selection = SimpleNamespace(coherent_threshold=floor,
                                stack_max_share=settings.stack_max_share)
    return np.array([s["z"] for s in stack_seeds(flipped, seeds, bore_q, timestamps,
                                                 beam_sigma, row_step, settings.stack_window,
                                                 selection)])


def stack_at(maps, bore_q, ra, dec, t_lo, t_hi, row_reach):
    """:func:`stack` of (ra, dec) over the maps between ctimes ``t_lo`` and ``t_hi`` (None
    when fewer than two crossings are found)."""
    crossings = [c for c in (crossing_of(m, bore_q, ra, dec, row_reach) for m in maps
                             if m.t_hi >= t_lo and m.t_lo <= t_hi) if c is not None]
    return stack(crossings) if len(crossings) >= 2 else None


def suppress(stacks, timestamps, radius):
    """The highest of stacks within ``radius`` (rad) of each other whose crossings overlap
    in time."""
    kept = []
    for s in sorted(stacks, key=lambda s: -s["z"]):
        span = _span(s, timestamps)
        if not any(sky_separation(s["ra"], s["dec"], k["ra"], k["dec"]) <= radius
                   and span[0] <= _span(k, timestamps)[1]
                   and _span(k, timestamps)[0] <= span[1] for k in kept):
            kept.append(s)
    return kept


def _span(s, timestamps):
    t = timestamps[[c.sample for c in s["crossings"]]]
    return t.min(), t.max()
