"""Candidate search: high-S/N samples, split into single scans, clustered on the sky with DBSCAN.

Paper, section 4.1: samples with S/N >= 3 from all detectors of a group (wafer x band) are split
at the scan turnarounds; within each scan their RA/Dec (computed for these samples only) are
clustered with DBSCAN at the beam scale ``sigma_FWHM = FWHM / (2 sqrt(ln 2))``, and clusters of
more than 10 samples become candidates. Each candidate is one crossing of the array by a
possible source, or part of one: where the detectors' tracks lie farther apart across the
scan than sigma_FWHM (the UHF bands; f150 barely), a source between two tracks gives a
cluster on each side. Both are kept here, as the paper's method makes them; ``transient_fit``
then reports one detection per crossing
(:func:`so_transients.detect.fit_candidates.crossing_duplicates`).

Everything here works on plain arrays; the sky positions come from a callable so the caller
decides how pointing is computed (see :func:`so_transients.common.pointing.radec_of_samples`).
Candidates are dicts of arrays with the ``transient_find`` columns of
:mod:`so_transients.common.candidates`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import ndimage

from so_transients.common import candidates
from so_transients.common.angles import ARCMIN, mean_direction, tangent_offsets
from so_transients.detect.dbscan import dbscan_labels
from so_transients.common.scan_geometry import constant_velocity, samples_in
from so_transients.common.step_config import ConfigError, non_negative, positive, setting

log = logging.getLogger(__name__)


MODES = ("paper", "coherent")
#: ``transient_find``'s scan index per sample in the AxisManager (-1: not searched)
SCAN_FIELD = "transient_scan"


@dataclass
class FindConfig:
    snr_threshold: float = setting(
        3.0, "S/N",
        "paper mode: samples with matched-filter S/N at least this are clustered")
    eps_arcmin: float | None = setting(None, "arcmin", "DBSCAN scale; null: sigma_FWHM of the band")
    dbscan_min_samples: int = setting(5, "", "DBSCAN core-point neighbourhood (scikit-learn default)")
    min_cluster_samples: int = setting(11, "", "fewest samples of a cluster (the paper's \"more than 10\")")
    min_dets: int = setting(
        5, "",
        "fewest detectors of a candidate (paper mode: of a cluster; coherent mode: live detectors a band "
        "needs)")
    max_candidates: int = setting(2000, "", "most candidates per group; the rest are dropped with a warning")
    speed_tolerance: float = setting(
        0.1, "",
        "samples scanning further than this fraction off the nominal scan speed are not searched")
    turnaround_buffer: float = setting(
        0.0, "s",
        "left out around the samples off the nominal scan speed (turnarounds)")
    archive_slots: int = setting(4, "", "catalogue cells per detector in the archive")
    mode: str = setting(
        "paper", "",
        "\"paper\": S/N >= 3 clusters; \"coherent\": maxima of Z (its settings: "
        "so_transients.coherent.config)")

    def __post_init__(self):
        if not self.snr_threshold >= 2.0:
            # every sample above it is clustered: at S/N 2, 2.3 % of an hour of a wafer-band
            # (15 million samples); at 1, 16 %, more than a worker's memory
            raise ConfigError(f"transient_find: snr_threshold must be at least 2, got "
                              f"{self.snr_threshold}")
        non_negative("transient_find", turnaround_buffer=self.turnaround_buffer)
        positive("transient_find", dbscan_min_samples=self.dbscan_min_samples,
                 min_cluster_samples=self.min_cluster_samples, min_dets=self.min_dets,
                 max_candidates=self.max_candidates, speed_tolerance=self.speed_tolerance,
                 archive_slots=self.archive_slots, eps_arcmin=self.eps_arcmin)
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")

    @property
    def eps(self):
        """The DBSCAN scale in radians, None for each band's sigma_FWHM."""
        return None if self.eps_arcmin is None else self.eps_arcmin * ARCMIN


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
    return tangent_offsets(ra, dec, *mean_direction(ra, dec))


def mean_radec(ra, dec):
    """Mean direction of points on the sphere, RA in [0, 2 pi) (handles RA wrap-around)."""
    ra0, dec0 = mean_direction(ra, dec)
    return float(np.mod(ra0, 2 * np.pi)), float(dec0)


CLUSTER_FIELDS = ("scan", "direction", "cluster_ra", "cluster_dec", "t_median", "t_start",
                  "t_stop", "t_peak", "snr_max", "n_samples", "n_dets", "peak_det")


def find_candidates(snr, timestamps, scan, directions, radec, eps, cfg: FindConfig, rows=None,
                    cap=None):
    """Cluster high-S/N samples into candidates.

    ``snr`` (ndet, nsamps), of which only ``rows`` (default all) are searched, and detector
    indices count within them; ``scan`` from :func:`scan_segments`; ``radec(dets, samps)``
    returns RA, Dec (radians) of the given samples; ``eps`` in radians. Returns
    ``(candidates, hits)``: dicts of arrays, one row per candidate (fields
    :data:`CLUSTER_FIELDS`) and one row per sample that belongs to a candidate (the columns
    of :data:`so_transients.common.candidates.HIT_COLUMNS`), at most ``cap`` candidates (default
    ``cfg.max_candidates``; ``cap=False``: no cap).
    """
    dets, samps, values = select_samples(snr, cfg.snr_threshold, scan >= 0, rows)
    ra, dec = radec(dets, samps)
    cands = {k: [] for k in CLUSTER_FIELDS}
    hits = {k: [] for k in candidates.HIT_COLUMNS}
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
    cands, hits = as_arrays(cands, hits)
    if cap is False:
        return cands, hits
    return cap_candidates(cands, hits, cfg.max_candidates if cap is None else cap)


def as_arrays(cands, hits):
    """Candidate and hit columns collected as lists, as arrays (hits in their dtypes)."""
    cands = {k: np.asarray(v) for k, v in cands.items()}
    hits = {k: np.asarray(v, dtype) for (k, v), dtype in zip(hits.items(),
                                                             candidates.HIT_COLUMNS.values())}
    return cands, hits


def _add_candidate(cands, hits, members, scan, direction, dets, samps, values, ra, dec, t):
    cid = len(cands["scan"])
    best = members[np.argmax(values[members])]
    times = t[samps[members]]
    c_ra, c_dec = mean_radec(ra[members], dec[members])
    for key, value in (("scan", scan), ("direction", direction), ("cluster_ra", c_ra),
                       ("cluster_dec", c_dec), ("t_median", np.median(times)),
                       ("t_start", times.min()), ("t_stop", times.max()),
                       ("t_peak", t[samps[best]]), ("snr_max", values[best]),
                       ("n_samples", len(members)), ("n_dets", len(np.unique(dets[members]))),
                       ("peak_det", dets[best])):
        cands[key].append(value)
    for key, value in (("det", dets[members]), ("samp", samps[members]),
                       ("snr", values[members]), ("ra", ra[members]), ("dec", dec[members])):
        hits[key].extend(value)
    hits["cand"].extend([cid] * len(members))


def searchable_scans(at_speed, timestamps, az, cfg: FindConfig):
    """Scan index per sample (-1 where nothing is searched) and each scan's direction.

    Searched: every sample ``at_speed`` (scanning within ``cfg.speed_tolerance`` of the
    template's speed: :func:`so_transients.common.scan_geometry.constant_velocity`), which is the
    whole constant-velocity part of each sweep up to its first and last sample; the
    turnarounds themselves, where the speed falls towards zero, split the scans.
    ``cfg.turnaround_buffer`` seconds around the off-speed samples may be left out as well (0
    by default: the filter runs over the whole TOD, so nothing rings at the scan ends; a
    larger value is for data whose turnarounds excite the telescope). Turnaround flags of the
    standard steps are not used: their buffers (sotodlib's ``t_buffer``) reach into the
    constant-velocity part, which would go unsearched.
    """
    skip = ~np.asarray(at_speed, bool)
    n_buf = samples_in(timestamps, cfg.turnaround_buffer)
    if n_buf and skip.any():
        skip = ndimage.maximum_filter1d(skip.view(np.uint8), 2 * n_buf + 1).astype(bool)
    return scan_segments(skip, np.asarray(az))


def group_scans(timestamps, az, el, cfg: FindConfig, where=""):
    """:func:`searchable_scans` of a group's boresight: the scans ``transient_find``
    searches, for the steps and commands that need them again."""
    at_speed = constant_velocity(timestamps, az, el, cfg.speed_tolerance, where)
    return searchable_scans(at_speed, timestamps, az, cfg)


def find_group_candidates(snr, timestamps, scan, directions, radec, bands, wafers, eps_by_band,
                          cfg: FindConfig, cap, where=""):
    """Candidates of a whole group (every band of it), at most ``cap`` of them (highest S/N).

    ``bands``, ``wafers``: per detector (row of ``snr``); ``radec(dets, samps)`` with group
    detector indices; ``eps_by_band``: DBSCAN scale (radians) per band. Returns
    ``(candidates, hits)`` with every ``transient_find`` column of the schema, detector
    indices counting in the group.
    """
    parts = []
    for band in sorted(set(bands)):
        dets = np.flatnonzero(bands == band)
        c, h = find_candidates(snr, timestamps, scan, directions,
                               lambda d, s, dets=dets: radec(dets[d], s), eps_by_band[band],
                               cfg, rows=dets, cap=False)
        c["map_z"] = np.full(len(c["scan"]), np.nan)
        c["n_crossings"] = np.ones(len(c["scan"]), int)
        parts.append(band_part(c, h, dets, band, wafers))
    return merge_bands(parts, cap, where)


def band_part(cands, hits, dets, band, wafers):
    """One band's ``(candidates, hits)`` with detector indices counting in the group
    (``dets``: the group indices of the rows they counted in), its band and wafer."""
    cands["peak_det"], hits["det"] = dets[cands["peak_det"].astype(int)], dets[hits["det"]]
    cands["bandpass"] = np.full(len(cands["scan"]), band)
    candidates.fill_missing(cands, candidates.JOINT_FIND_COLUMNS, len(cands["scan"]))
    cands["wafer_slot"] = np.asarray(wafers)[cands["peak_det"]]
    return cands, hits


def merge_bands(parts, cap, where=""):
    """The bands' ``(candidates, hits)`` as one group's, at most ``cap`` candidates (highest
    S/N), numbered, every ``transient_find`` column checked."""
    if not parts:
        return candidates.empty("transient_find"), candidates.empty_hits()
    cands, hits = {}, {}
    offset = 0
    for c, h in parts:
        h["cand"] = h["cand"] + offset
        offset += len(c["scan"])
        for store, part in ((cands, c), (hits, h)):
            for k, v in part.items():
                store[k] = np.concatenate([store[k], v]) if k in store else v
    cands, hits = cap_candidates(cands, hits, cap, where)
    cands["cand_id"] = np.arange(len(cands["scan"]))
    return candidates.check(cands, "transient_find"), hits


def cap_candidates(cands, hits, max_candidates, where=""):
    """Keep the ``max_candidates`` candidates of highest S/N (coherent mode: highest
    ``map_z``) with a warning, renumbering hits."""
    n = len(cands["scan"])
    if n <= max_candidates:
        return cands, hits
    log.warning("%s%d candidates found, more than the cap of %d: keeping the %d with the "
                "highest S/N (a glitch storm or a very bright source?)",
                f"{where}: " if where else "", n, max_candidates, max_candidates)
    rank = cands.get("map_z")
    rank = cands["snr_max"] if rank is None or not np.isfinite(rank).all() else rank
    joint = cands.get("joint_z")      # a joint-band search's candidates: by J
    rank = joint if joint is not None and np.isfinite(joint).all() else rank
    keep = np.sort(np.argsort(-rank, kind="stable")[:max_candidates])
    renumber = np.full(n, -1)
    renumber[keep] = np.arange(len(keep))
    cands = {k: v[keep] for k, v in cands.items()}
    in_kept = renumber[hits["cand"]] >= 0
    hits = {k: v[in_kept] for k, v in hits.items()}
    hits["cand"] = renumber[hits["cand"]]
    return cands, hits
