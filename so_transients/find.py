"""Candidate search: high-S/N samples, split into single scans, clustered on the sky with DBSCAN.

Paper, section 4.1: samples with S/N >= 3 from all detectors of a group (wafer x band) are split
at the scan turnarounds; within each scan their RA/Dec (computed for these samples only) are
clustered with DBSCAN at the beam scale ``sigma_FWHM = FWHM / (2 sqrt(ln 2))``, and clusters of
more than 10 samples become candidates. Each candidate is one crossing of the array by a
possible source.

Everything here works on plain arrays; the sky positions come from a callable so the caller
decides how pointing is computed (see :func:`so_transients.pointing.radec_of_samples`).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numba import njit

from .dbscan import dbscan_labels

log = logging.getLogger(__name__)

CANDIDATE_FIELDS = ("scan", "direction", "ra", "dec", "t_median", "t_start", "t_stop",
                    "t_peak", "snr_max", "n_samples", "n_dets", "peak_det")


@dataclass
class FindConfig:
    snr_threshold: float = 3.0
    eps: float | None = None          # DBSCAN scale (radians); None: sigma_FWHM of the band
    dbscan_min_samples: int = 5       # DBSCAN core-point neighbourhood (scikit-learn default)
    min_cluster_samples: int = 11     # "more than 10 samples"
    min_dets: int = 5                 # clusters on fewer detectors cannot pass the cuts
    max_candidates: int = 2000        # per group; the rest are dropped with a warning


def scan_segments(in_turnaround, az):
    """Scan index per sample (-1 inside turnarounds) and each scan's direction (+1 / -1 in az).

    Scans are the maximal runs of samples outside turnarounds.
    """
    in_turnaround = np.asarray(in_turnaround, bool)
    moving = ~in_turnaround
    starts = np.flatnonzero(moving & ~np.concatenate([[False], moving[:-1]]))
    scan = np.cumsum(np.isin(np.arange(len(moving)), starts)) - 1
    scan[~moving] = -1
    directions = np.zeros(len(starts), int)
    for k in range(len(starts)):
        sel = np.flatnonzero(scan == k)
        step = az[sel[-1]] - az[sel[0]] if len(sel) > 1 else 0.0
        directions[k] = 1 if step >= 0 else -1
    return scan, directions


def select_samples(snr, threshold, searchable=None, rows=None):
    """(row, sample) indices and S/N of the samples with ``snr >= threshold``.

    ``searchable``: optional (nsamps,) bool, samples that may be selected (scans, not
    turnarounds); ``rows``: optional indices of the rows of ``snr`` to search (the returned
    row indices count within them). One compiled pass over the rows, without copying them.
    """
    snr = np.asarray(snr)
    rows = np.arange(len(snr)) if rows is None else np.asarray(rows, np.int64)
    searchable = (np.ones(snr.shape[1], bool) if searchable is None
                  else np.ascontiguousarray(searchable, bool))
    counts = _count_above(snr, rows, np.float32(threshold), searchable)
    dets = np.repeat(np.arange(len(rows)), counts)
    samps = np.empty(counts.sum(), np.int64)
    values = np.empty(counts.sum(), np.float32)
    _fill_above(snr, rows, np.float32(threshold), searchable, samps, values)
    return dets, samps, values


@njit(cache=True, nogil=True)
def _count_above(snr, rows, threshold, searchable):
    counts = np.zeros(len(rows), np.int64)
    for i in range(len(rows)):
        row = snr[rows[i]]
        n = 0
        for s in range(len(row)):
            if row[s] >= threshold and searchable[s]:
                n += 1
        counts[i] = n
    return counts


@njit(cache=True, nogil=True)
def _fill_above(snr, rows, threshold, searchable, samps, values):
    k = 0
    for i in range(len(rows)):
        row = snr[rows[i]]
        for s in range(len(row)):
            if row[s] >= threshold and searchable[s]:
                samps[k] = s
                values[k] = row[s]
                k += 1


def _tangent_plane(ra, dec):
    """Flat coordinates (radians) around the points' mean direction."""
    vec = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)])
    mean = vec.mean(axis=1)
    ra0, dec0 = np.arctan2(mean[1], mean[0]), np.arctan2(mean[2], np.hypot(mean[0], mean[1]))
    dra = np.angle(np.exp(1j * (ra - ra0)))
    return np.c_[dra * np.cos(dec0), dec - dec0]


def mean_radec(ra, dec):
    """Mean direction of points on the sphere (handles RA wrap-around)."""
    vec = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)]).mean(axis=1)
    return float(np.mod(np.arctan2(vec[1], vec[0]), 2 * np.pi)), \
        float(np.arctan2(vec[2], np.hypot(vec[0], vec[1])))


def find_candidates(snr, timestamps, scan, directions, radec, eps, cfg: FindConfig, rows=None):
    """Cluster high-S/N samples into candidates.

    ``snr`` (ndet, nsamps), of which only ``rows`` (default all) are searched, and detector
    indices count within them; ``scan`` from :func:`scan_segments`; ``radec(dets, samps)``
    returns RA, Dec (radians) of the given samples; ``eps`` in radians. Returns
    ``(candidates, hits)``: dicts of arrays, one row per candidate (fields
    :data:`CANDIDATE_FIELDS`) and one row per sample that belongs to a candidate (``cand``,
    ``det``, ``samp``, ``snr``, ``ra``, ``dec``).
    """
    dets, samps, values = select_samples(snr, cfg.snr_threshold, scan >= 0, rows)
    ra, dec = radec(dets, samps)
    cands = {k: [] for k in CANDIDATE_FIELDS}
    hits = {k: [] for k in ("cand", "det", "samp", "snr", "ra", "dec")}
    for k in np.unique(scan[samps]):
        sel = np.flatnonzero(scan[samps] == k)
        if len(sel) < cfg.min_cluster_samples:
            continue
        labels = dbscan_labels(_tangent_plane(ra[sel], dec[sel]), eps, cfg.dbscan_min_samples)
        for label in np.unique(labels[labels >= 0]):
            members = sel[labels == label]
            if (len(members) < cfg.min_cluster_samples
                    or len(np.unique(dets[members])) < cfg.min_dets):
                continue
            _add_candidate(cands, hits, members, k, directions[k], dets, samps, values, ra, dec,
                           timestamps)
    cands = {k: np.asarray(v) for k, v in cands.items()}
    hits = {k: np.asarray(v) for k, v in hits.items()}
    return cap_candidates(cands, hits, cfg.max_candidates)


def _add_candidate(cands, hits, members, scan, direction, dets, samps, values, ra, dec, t):
    cid = len(cands["scan"])
    best = members[np.argmax(values[members])]
    times = t[samps[members]]
    c_ra, c_dec = mean_radec(ra[members], dec[members])
    for key, value in (("scan", scan), ("direction", direction), ("ra", c_ra), ("dec", c_dec),
                       ("t_median", np.median(times)), ("t_start", times.min()),
                       ("t_stop", times.max()), ("t_peak", t[samps[best]]),
                       ("snr_max", values[best]), ("n_samples", len(members)),
                       ("n_dets", len(np.unique(dets[members]))), ("peak_det", dets[best])):
        cands[key].append(value)
    for key, value in (("det", dets[members]), ("samp", samps[members]),
                       ("snr", values[members]), ("ra", ra[members]), ("dec", dec[members])):
        hits[key].extend(value)
    hits["cand"].extend([cid] * len(members))


def cap_candidates(cands, hits, max_candidates, where=""):
    """Keep the ``max_candidates`` candidates of highest S/N (with a warning), renumbering hits."""
    n = len(cands["scan"])
    if n <= max_candidates:
        return cands, hits
    log.warning("%s%d candidates found, more than the cap of %d: keeping the %d with the "
                "highest S/N (a glitch storm or a very bright source?)",
                f"{where}: " if where else "", n, max_candidates, max_candidates)
    keep = np.sort(np.argsort(-cands["snr_max"], kind="stable")[:max_candidates])
    renumber = np.full(n, -1)
    renumber[keep] = np.arange(len(keep))
    cands = {k: v[keep] for k, v in cands.items()}
    in_kept = renumber[hits["cand"]] >= 0
    hits = {k: v[in_kept] for k, v in hits.items()}
    hits["cand"] = renumber[hits["cand"]]
    return cands, hits
