"""Joining detections into events, and events into sources.

One flare crossed by three wafers in two bands over several sweeps is detected many times.
:func:`link` joins detections (friends of friends) when their positions agree within
``n_sigma`` combined position errors (never less than ``min_separation``, the systematic
part) and their times are within ``max_gap`` of each other: an event is a chain of such
detections, so a long flare seen sweep after sweep stays one event while two flares 10 arcmin
apart, or at one position hours apart, stay two. :func:`link` on the events' positions with
a night-long ``max_gap`` then gives the sources (the same position seen again, in another
observation of the night). All angles in radians, times in ctime seconds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from so_transients.common.angles import ARCMIN, ARCSEC
from so_transients.common.step_config import setting


@dataclass
class AssociationConfig:
    n_sigma: float = setting(5.0, "", "positions agree within this many combined errors ...")
    min_separation_arcsec: float = setting(
        30.0, "arcsec", "... or this close (pointing systematics)")
    max_separation_arcmin: float = setting(
        5.0, "arcmin", "never farther (a poorly measured position)")
    max_gap_s: float = setting(600.0, "s", "detections of one event at most this far apart in time")
    source_gap_hours: float = setting(
        24.0, "h", "events of one source (same position) within this time")

    @property
    def min_separation(self):
        return self.min_separation_arcsec * ARCSEC

    @property
    def max_separation(self):
        return self.max_separation_arcmin * ARCMIN


def unit_vectors(ra, dec):
    ra, dec = np.asarray(ra, float), np.asarray(dec, float)
    return np.c_[np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)]


def position_sigma(ra_err, dec_err):
    """One-axis position error (radians) of positions with errors ``ra_err`` (along RA on the
    sky) and ``dec_err``: their quadratic mean (NaN for unknown errors)."""
    return np.sqrt((np.asarray(ra_err, float) ** 2 + np.asarray(dec_err, float) ** 2) / 2)


def link(ra, dec, sigma, t, cfg: AssociationConfig, max_gap=None):
    """Group labels (0 .. n_groups - 1, in order of first time) of positions linked friends
    of friends: separation <= clip(n_sigma x hypot(sigma_i, sigma_j), min_separation,
    max_separation) and |t_i - t_j| <= ``max_gap`` (default ``cfg.max_gap_s``). ``t``: one
    time per position, or (start, stop) pairs (n, 2) for spans, whose gap is then the time
    between the spans."""
    n = len(np.atleast_1d(ra))
    if n == 0:
        return np.zeros(0, int)
    max_gap = cfg.max_gap_s if max_gap is None else max_gap
    span = np.asarray(t, float).reshape(n, -1)
    start, stop = span[:, 0], span[:, -1]
    sigma = np.nan_to_num(np.asarray(sigma, float), nan=cfg.max_separation)
    vec = unit_vectors(ra, dec)
    pairs = cKDTree(vec).query_pairs(2 * np.sin(cfg.max_separation / 2), output_type="ndarray")
    i, j = pairs.T if len(pairs) else (np.zeros(0, int), np.zeros(0, int))
    sep = 2 * np.arcsin(np.clip(np.linalg.norm(vec[i] - vec[j], axis=1) / 2, 0, 1))
    limit = np.clip(cfg.n_sigma * np.hypot(sigma[i], sigma[j]), cfg.min_separation,
                    cfg.max_separation)
    gap = np.maximum(start[i], start[j]) - np.minimum(stop[i], stop[j])
    ok = (sep <= limit) & (gap <= max_gap)
    graph = coo_matrix((np.ones(ok.sum()), (i[ok], j[ok])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    first = np.array([start[labels == k].min() for k in range(labels.max() + 1)])
    order = np.argsort(np.argsort(first, kind="stable"), kind="stable")
    return order[labels]


def weighted_position(ra, dec, sigma):
    """``(ra, dec, sigma)``: the inverse-variance weighted mean of positions with one-axis
    errors ``sigma`` (equal weights where errors are unknown) and its error."""
    sigma = np.asarray(sigma, float)
    known = np.isfinite(sigma) & (sigma > 0)
    w = np.where(known, sigma**-2.0, 0.0) if known.any() else np.ones(len(sigma))
    mean = (unit_vectors(ra, dec) * w[:, None]).sum(axis=0)
    mean /= np.linalg.norm(mean)
    err = float(np.sum(w) ** -0.5) if known.any() else np.nan
    return (float(np.mod(np.arctan2(mean[1], mean[0]), 2 * np.pi)),
            float(np.arcsin(np.clip(mean[2], -1, 1))), err)
