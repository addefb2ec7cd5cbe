"""Time slides of sweep stacks: a background for stacked candidates many times the data's.

A sweep stack (:mod:`so_transients.coherent.sweep_stack`) adds one sky position's crossings of
several scans' maps. The sign-inverted maps' stacks give it a background with one data live
time behind it. A stack slide moves each scan's map along its scan by its own random
cyclic offset (at least ``min_shift`` samples): a real source's crossings no longer line up
from scan to scan, while each map keeps its own noise, the correlation of its neighbouring
positions and its glitches. As in gravitational-wave time slides, where one detector is held
and the others are moved, each seed (a data map's maximum from ``stack_seed``, found as
``transient_find`` finds them) stays where it is and the maps of its other crossings move.
The crossings' map cells are found once; a slide only reads them elsewhere, so ``n_slides``
slides cost array look-ups, not pointing.

A slid stack is selected as the data's (:func:`so_transients.coherent.sweep_stack.kept`: at least
the floor, higher than each of its crossings, no crossing more than ``stack_max_share`` of
its sum), and of a scan's seeds within ``radius`` of each other the highest is kept (seeds
of different scans no longer share a position once their maps move). The background's live
time is ``n_slides`` times the data's.

Everything here is on arrays and :class:`so_transients.coherent.sweep_stack.ScanMap`; no AxisManager.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from so_transients.common.angles import sky_separation
from so_transients.coherent.sweep_stack import StackSettings, crossing_cells


@dataclass
class SeedCells:
    """Where each seed's crossings are on the maps: one entry per crossing, grouped by seed
    (``starts``: each seed's first entry)."""

    starts: np.ndarray        # (nseed,) first entry of each seed
    scan: np.ndarray          # (nseed,) the seed's scan
    ra: np.ndarray            # (nseed,) rad
    dec: np.ndarray
    map_index: np.ndarray     # (nentry,) the map crossed
    row: np.ndarray           # (nentry,) its row index and sample on that map
    t: np.ndarray
    held: np.ndarray          # (nentry,) the seed's own map: not moved
    n: np.ndarray             # (nentry,) the row's inverse flux noise


def seed_cells(maps, seeds, bore_q, timestamps, row_reach, window_s) -> SeedCells:
    """The :class:`SeedCells` of ``seeds`` (``(scan, sample, ra, dec)``) on the ``maps``
    within ``window_s`` centred on each: seeds whose own crossing is off their map, or that
    cross no other map, are left out."""
    seeds = np.array(seeds, float).reshape(-1, 4)
    scan, ra, dec = seeds[:, 0].astype(int), seeds[:, 2], seeds[:, 3]
    t = timestamps[seeds[:, 1].astype(np.int64)]
    parts = []                 # (seed, map, row, t0, held, n) of each map's crossings
    for j, m in enumerate(maps):
        near = np.flatnonzero((m.t_hi >= t - window_s / 2) & (m.t_lo <= t + window_s / 2))
        row, t0, ok = crossing_cells(m, bore_q, ra[near], dec[near], row_reach)
        held = scan[near] == m.scan
        ok &= ~held | np.isfinite(m.z[row, t0])     # a seed's own value is read as it is
        parts.append((near[ok], np.full(ok.sum(), j), row[ok], t0[ok], held[ok],
                      m.n[row[ok]]))
    seed, index, row, t0, held, n = (np.concatenate([p[k] for p in parts] or [[]])
                                     for k in range(6))
    order = np.argsort(seed, kind="stable")
    seed, index, row, t0, held, n = (a[order] for a in (seed, index, row, t0, held, n))
    count = np.bincount(seed.astype(np.int64), minlength=len(seeds))
    has_own = np.bincount(seed.astype(np.int64), weights=held, minlength=len(seeds)) > 0
    good = (count >= 2) & has_own
    keep = good[seed.astype(np.int64)]
    starts = (np.cumsum(count[good]) - count[good]).astype(np.int64)
    return SeedCells(starts, scan[good], ra[good], dec[good], index[keep].astype(np.int64),
                     row[keep].astype(np.int64), t0[keep].astype(np.int64),
                     held[keep].astype(bool), n[keep].astype(float))


def slide_offsets(maps, n_slides, min_shift, rng) -> np.ndarray:
    """``(n_slides, nmap)`` cyclic offsets (samples) of each map in each slide, from
    ``min_shift`` to its length less ``min_shift``; -1 for a map too short to move that
    far (its crossings are left out of the slides)."""
    out = np.full((n_slides, len(maps)), -1, np.int64)
    for j, m in enumerate(maps):
        nsamp = m.z.shape[1]
        if nsamp > 2 * min_shift:
            out[:, j] = rng.integers(min_shift, nsamp - min_shift + 1, n_slides)
    return out


def slid_values(maps, cells: SeedCells, offsets) -> np.ndarray:
    """``(n_slides, nentry)`` Z at each crossing in each slide: the seed's own map as it is,
    every other map read ``offsets`` samples earlier (cyclically; NaN where a map cannot
    move)."""
    out = np.full((len(offsets), len(cells.row)), np.nan, np.float32)
    for j, m in enumerate(maps):
        e = np.flatnonzero(cells.map_index == j)
        if not len(e):
            continue
        shift = np.where(cells.held[e], 0, offsets[:, [j]])
        out[:, e] = np.where(shift >= 0, m.z[cells.row[e], (cells.t[e] - shift) % m.z.shape[1]],
                             np.nan)
    return out


def stack_statistics(values, cells: SeedCells) -> dict:
    """Per slide and seed (``(n_slides, nseed)`` arrays): the stack's ``z``, its highest
    single crossing ``best``, the largest crossing's ``share`` of its sum, and ``count``,
    the crossings with a value (:func:`so_transients.coherent.sweep_stack.stack` on each)."""
    finite = np.isfinite(values)
    terms = np.where(finite, cells.n * values, 0.0)
    total = np.add.reduceat(terms, cells.starts, axis=1)
    norm2 = np.add.reduceat(np.where(finite, cells.n**2, 0.0), cells.starts, axis=1)
    largest = np.maximum.reduceat(np.where(finite, terms, -np.inf), cells.starts, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = total / np.sqrt(norm2)
        share = np.where(total > 0, largest / total, 1.0)
    return dict(z=z, share=share, count=np.add.reduceat(finite, cells.starts, axis=1),
                best=np.maximum.reduceat(np.where(finite, values, -np.inf), cells.starts,
                                         axis=1))


def neighbours(cells: SeedCells, radius) -> np.ndarray:
    """``(nseed, nseed)``: seeds of one scan within ``radius`` (rad) of each other."""
    same = cells.scan[:, None] == cells.scan[None, :]
    near = sky_separation(cells.ra[:, None], cells.dec[:, None], cells.ra[None, :],
                          cells.dec[None, :]) <= radius
    return same & near


def strongest(z, candidates, near) -> list:
    """Of the seeds ``candidates`` (indices), the highest of each group of ``near`` ones."""
    kept = []
    for i in candidates[np.argsort(-z[candidates])]:
        if not near[i, kept].any():
            kept.append(i)
    return kept


def slid_stacks(maps, seeds, bore_q, timestamps, beam_sigma, row_step,
                settings: StackSettings, floor, n_slides, min_shift, rng) -> np.ndarray:
    """Z of the slid stacks of ``seeds`` (the data maps' seeds, ``(scan, sample, ra,
    dec)``) from ``floor`` up over ``n_slides`` slides of the ``maps``
    (:class:`so_transients.coherent.sweep_stack.ScanMap`, in units of their spread), selected as
    the data's stacks are: the background of stacked candidates over ``n_slides`` times the
    maps' live time."""
    cells = seed_cells(maps, seeds, bore_q, timestamps, row_step * beam_sigma,
                       settings.stack_window)
    if not len(cells.starts) or n_slides < 1:
        return np.zeros(0)
    stats = stack_statistics(slid_values(maps, cells, slide_offsets(maps, n_slides,
                                                                      min_shift, rng)),
                             cells)
    z = stats["z"]
    passing = ((stats["count"] >= 2) & (z >= floor) & (z > stats["best"])
               & (stats["share"] <= settings.stack_max_share))
    near = neighbours(cells, 2.0 * beam_sigma)
    found = [z[k, strongest(z[k], np.flatnonzero(passing[k]), near)]
             for k in range(n_slides) if passing[k].any()]
    return np.concatenate(found) if found else np.zeros(0)
