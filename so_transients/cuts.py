"""Candidate cuts (Clancy et al. 2025, section 4.2): is a candidate source-like?

For each candidate, from the focal-plane positions of its detectors and the time each of them
saw its highest S/N:

* ``n_dets``: at least ``min_dets`` distinct detectors;
* ``aspect_ratio``: the detectors form a line along the scan direction: (extent along the scan
  + pitch) / (extent across + pitch) of their focal-plane positions is at least
  ``min_aspect_ratio`` (the pitch regularizes single rows and single pixels);
* ``time_order``: the detectors were hit in the order and at the pace of a source drifting
  across the array: their peak times follow ``t = t0 + s / v`` (``s`` the position along the
  scan, ``v`` the drift speed) within ``time_tolerance`` seconds (robust rms, 1.4826 MAD, so
  that a few detectors peaking on noise do not reject a bright source), and better than "all at
  one instant" whenever the detectors span enough of the scan direction to tell. This is what
  rejects readout glitches and cosmic rays that hit many detectors at once;
* ``known_source``: no catalogued source within ``mask_radius`` (default sigma_FWHM).

The polarization flag (not a cut) marks candidates whose detectors mostly share one
polarization orientation (within +-22.5 deg), as a strongly polarized source would produce.

Cuts are evaluated in this order; ``cut_reason`` names the first that failed ('' if none).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from astropy import units as u
from astropy.table import Table

CUT_ORDER = ("n_dets", "aspect_ratio", "time_order", "known_source")


@dataclass
class CutsConfig:
    min_dets: int = 5
    min_aspect_ratio: float = 1.5
    time_tolerance: float = 0.02        # s, rms of peak times about the drift model
    catalog: str | None = None          # ECSV/CSV file with ra, dec columns
    catalog_unit: str = "deg"           # unit of ra/dec when the file does not carry one
    mask_radius: float | None = None    # radians; None: sigma_FWHM of the band
    pol_fraction: float = 0.8


def read_catalog(path, unit="deg"):
    """RA, Dec (radians) of the sources in an ECSV or CSV file with ``ra`` and ``dec`` columns."""
    table = Table.read(path, format="ascii.ecsv" if str(path).endswith(".ecsv") else None)
    missing = {"ra", "dec"} - set(table.colnames)
    if missing:
        raise ValueError(f"catalog {path} lacks columns {sorted(missing)}")
    out = []
    for name in ("ra", "dec"):
        col = table[name]
        quantity = col.quantity if col.unit is not None else np.asarray(col) * u.Unit(unit)
        out.append(quantity.to_value(u.rad))
    return out[0], out[1]


def line_extents(xi, eta, direction):
    """Extents (ptp) of points along and across a unit ``direction`` in the focal plane."""
    along = xi * direction[0] + eta * direction[1]
    across = -xi * direction[1] + eta * direction[0]
    return np.ptp(along), np.ptp(across), along


def robust_rms(x):
    """1.4826 x median absolute deviation: an rms that a few outliers do not inflate."""
    x = np.asarray(x, float)
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if len(x) else 0.0


def time_order(t_peak, along, speed, tolerance):
    """(passes, robust rms about the drift model, robust rms about one instant)."""
    r_drift = robust_rms(t_peak - along / speed)
    r_instant = robust_rms(t_peak)
    span = np.ptp(along) / abs(speed)
    passes = r_drift <= tolerance and (span <= 2 * tolerance or r_drift < r_instant)
    return passes, r_drift, r_instant


def dominant_orientation_fraction(gamma):
    """Largest fraction of angles (mod 180 deg) within +-22.5 deg of one of them."""
    theta = np.mod(np.asarray(gamma), np.pi)
    diff = np.abs(np.angle(np.exp(2j * (theta[:, None] - theta[None, :])))) / 2
    return float(((diff <= np.radians(22.5)).sum(axis=1)).max() / len(theta)) if len(theta) else 0.0


def near_catalog(ra, dec, cat_ra, cat_dec, radius):
    """True where (ra, dec) lies within ``radius`` of any catalogue position (all radians)."""
    if len(cat_ra) == 0 or len(ra) == 0:
        return np.zeros(len(ra), bool)
    cosd = (np.sin(dec)[:, None] * np.sin(cat_dec)[None]
            + np.cos(dec)[:, None] * np.cos(cat_dec)[None] * np.cos(ra[:, None] - cat_ra[None]))
    return (np.arccos(np.clip(cosd, -1, 1)) <= radius).any(axis=1)


def per_detector_peaks(hits, cand):
    """Detectors of candidate ``cand`` and the sample index where each had its highest S/N."""
    sel = np.flatnonzero(hits["cand"] == cand)
    order = sel[np.argsort(-hits["snr"][sel], kind="stable")]
    dets, first = np.unique(hits["det"][order], return_index=True)
    return dets, hits["samp"][order[first]]


def apply_cuts(cands, hits, xi, eta, gamma, timestamps, drift, pitch, cfg: CutsConfig,
               catalog=(np.zeros(0), np.zeros(0)), mask_radius=0.0):
    """Evaluate every cut for every candidate.

    ``xi``, ``eta``, ``gamma``: focal plane of the group's detectors (indexed by ``hits['det']``);
    ``drift``: (ncand, 2) velocity (rad/s) of each candidate's sky position across the focal
    plane; ``pitch``: detector spacing (radians). Returns a dict of per-candidate arrays:
    ``pass_<cut>`` for each cut, ``aspect_ratio``, ``time_rms``, ``instant_rms``,
    ``pol_fraction``, ``pol_flag``, ``cut_reason`` and ``passed``.
    """
    n = len(cands["scan"])
    out = {f"pass_{c}": np.zeros(n, bool) for c in CUT_ORDER}
    out.update(aspect_ratio=np.zeros(n), time_rms=np.zeros(n), instant_rms=np.zeros(n),
               pol_fraction=np.zeros(n), pol_flag=np.zeros(n, bool))
    near = near_catalog(cands["ra"], cands["dec"], catalog[0], catalog[1], mask_radius)
    for c in range(n):
        dets, samps = per_detector_peaks(hits, c)
        speed = float(np.hypot(*drift[c]))
        direction = drift[c] / speed
        along_ext, across_ext, along = line_extents(xi[dets], eta[dets], direction)
        ok_time, r_drift, r_inst = time_order(timestamps[samps], along, speed, cfg.time_tolerance)
        out["aspect_ratio"][c] = (along_ext + pitch) / (across_ext + pitch)
        out["time_rms"][c], out["instant_rms"][c] = r_drift, r_inst
        out["pass_n_dets"][c] = len(dets) >= cfg.min_dets
        out["pass_aspect_ratio"][c] = out["aspect_ratio"][c] >= cfg.min_aspect_ratio
        out["pass_time_order"][c] = ok_time
        out["pass_known_source"][c] = not near[c]
        out["pol_fraction"][c] = dominant_orientation_fraction(gamma[dets])
        out["pol_flag"][c] = len(dets) >= cfg.min_dets and out["pol_fraction"][c] >= cfg.pol_fraction
    reasons = np.full(n, "", dtype=object)
    for cut in reversed(CUT_ORDER):
        reasons[~out[f"pass_{cut}"]] = cut
    out["cut_reason"] = reasons.astype(str) if n else np.zeros(0, "U12")
    out["passed"] = np.all([out[f"pass_{c}"] for c in CUT_ORDER], axis=0) if n else np.zeros(0, bool)
    return out
