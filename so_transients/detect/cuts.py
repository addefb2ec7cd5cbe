"""Candidate cuts (Clancy et al. 2025, section 4.2): is a candidate source-like?

For each candidate, from the focal-plane positions of its detectors and the time each of them
saw its highest S/N:

* ``n_dets``: at least ``min_dets`` distinct detectors (``transient_find``'s setting: the
  same threshold, so clusters it keeps pass unless its ``min_dets`` is lowered later);
* ``aspect_ratio``: the detectors form a line along the scan direction: (extent along the scan
  + pitch) / (extent across + pitch) of their focal-plane positions is at least
  ``min_aspect_ratio`` (the pitch regularizes single rows and single pixels);
* ``time_order``: the detectors were hit in the order and at the pace of a source drifting
  across the array: their peak times follow ``t = t0 + s / v`` (``s`` the position along the
  scan, ``v`` the drift speed) within ``time_tolerance`` seconds (robust rms, 1.4826 MAD, so
  that a few detectors peaking on noise do not reject a bright source), and better than "all at
  one instant" whenever the detectors span enough of the scan direction to tell. This is what
  rejects readout glitches and cosmic rays that hit many detectors at once;
* ``sidelobe``: the candidate's detectors see no signal of the opposite sign more than
  ``max_opposite_ratio`` times stronger within ``sidelobe_window`` seconds: the matched
  filter's high-pass gives a strong negative signal (a bright source on sign-inverted data, a
  negative glitch or jump) positive sidelobes that cluster like a source a few arcmin away;
* ``known_source``: no source of the known-source list within ``mask_radius``
  (default sigma_FWHM).

The polarization flag (not a cut) marks candidates whose detectors mostly share one
polarization orientation (within +-22.5 deg), as a strongly polarized source would produce.

Cuts are evaluated in this order; ``cut_reason`` names the first that failed ('' if none).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from so_transients.common import candidates
from so_transients.common.angles import ARCMIN
from so_transients.common.sky_match import within_radius
from so_transients.detect.find import FindConfig
from so_transients.common.robust import mad_std
from so_transients.common.step_config import positive, share, setting

CUT_ORDER = ("n_dets", "aspect_ratio", "time_order", "sidelobe", "known_source")


@dataclass
class CutsConfig:
    min_aspect_ratio: float = setting(
        1.5, "",
        "detectors must form a line along the scan: focal-plane extent along / across the scan at least this")
    time_tolerance: float = setting(0.02, "s", "rms of peak times about the drift model")
    known_sources: str | None = setting(None, "", "ECSV/CSV with ra, dec, or a socat URL (socat:///x.db)")
    known_sources_unit: str = setting("deg", "", "unit of ra/dec when the file does not carry one")
    mask_radius_arcmin: float | None = setting(
        None, "arcmin",
        "known-source mask radius; null: sigma_FWHM of the band")
    pol_fraction: float = setting(
        0.8, "",
        "polarization flag (not a cut) when at least this fraction of the detectors share one orientation")
    sidelobe_window: float = setting(
        1.0, "s",
        "around the candidate's peaks searched for a signal of opposite sign")
    max_opposite_ratio: float = setting(
        2.0, "",
        "cut when a signal of opposite sign within sidelobe_window is this many times stronger (a filter "
        "sidelobe of a strong negative signal)")

    def __post_init__(self):
        positive("transient_cuts", min_aspect_ratio=self.min_aspect_ratio,
                 time_tolerance=self.time_tolerance, mask_radius_arcmin=self.mask_radius_arcmin,
                 pol_fraction=self.pol_fraction, sidelobe_window=self.sidelobe_window,
                 max_opposite_ratio=self.max_opposite_ratio)
        share("transient_cuts", pol_fraction=self.pol_fraction)

    @property
    def mask_radius(self):
        """Known-source mask radius in radians, None for each band's sigma_FWHM."""
        return None if self.mask_radius_arcmin is None else self.mask_radius_arcmin * ARCMIN


def line_extents(xi, eta, direction):
    """Extents (ptp) of points along and across a unit ``direction`` in the focal plane."""
    along = xi * direction[0] + eta * direction[1]
    across = -xi * direction[1] + eta * direction[0]
    return np.ptp(along), np.ptp(across), along


def time_order(t_peak, along, speed, tolerance):
    """(passes, robust rms about the drift model, robust rms about one instant)."""
    r_drift = float(mad_std(t_peak - along / speed))
    r_instant = float(mad_std(t_peak))
    span = np.ptp(along) / abs(speed)
    passes = r_drift <= tolerance and (span <= 2 * tolerance or r_drift < r_instant)
    return passes, r_drift, r_instant


def dominant_orientation_fraction(gamma):
    """Largest fraction of angles (mod 180 deg) within +-22.5 deg of one of them."""
    theta = np.mod(np.asarray(gamma), np.pi)
    diff = np.abs(np.angle(np.exp(2j * (theta[:, None] - theta[None, :])))) / 2
    return float(((diff <= np.radians(22.5)).sum(axis=1)).max() / len(theta)) if len(theta) else 0.0


def near_known_source(ra, dec, known_ra, known_dec, radius):
    """True where (ra, dec) lies within ``radius`` of any known source (all radians)."""
    return within_radius(ra, dec, known_ra, known_dec, radius)


def per_detector_peaks(hits, cand):
    """Detectors of candidate ``cand`` and the sample index where each had its highest S/N."""
    sel = np.flatnonzero(hits["cand"] == cand)
    order = sel[np.argsort(-hits["snr"][sel], kind="stable")]
    dets, first = np.unique(hits["det"][order], return_index=True)
    return dets, hits["samp"][order[first]]


def opposite_peak(snr, dets, samps, half_window):
    """Most negative S/N of detectors ``dets`` within ``half_window`` samples of ``samps``
    (their peak samples); 0 without data."""
    if snr is None or not len(dets):
        return 0.0
    lo = max(int(samps.min()) - half_window, 0)
    hi = min(int(samps.max()) + half_window + 1, snr.shape[1])
    block = np.asarray(snr[np.sort(dets), lo:hi])
    return float(min(block.min(), 0.0)) if block.size else 0.0


def apply_cuts(cands, hits, xi, eta, gamma, timestamps, drift, pitch, cfg: CutsConfig,
               known=(np.zeros(0), np.zeros(0)), mask_radius=0.0, snr=None,
               min_dets=FindConfig.min_dets):
    """Evaluate every cut for every candidate.

    ``xi``, ``eta``, ``gamma``: focal plane of the group's detectors (indexed by ``hits['det']``);
    ``drift``: (ncand, 2) velocity (rad/s) of each candidate's sky position across the focal
    plane; ``pitch``: detector spacing (radians). Returns a dict of per-candidate arrays:
    ``pass_<cut>`` for each cut, ``aspect_ratio``, ``time_rms``, ``instant_rms``,
    ``opposite_snr``, ``pol_fraction``, ``pol_flag``, ``cut_reason`` and ``passed``. ``snr``:
    the S/N (ndet, nsamps) the hits were found in, for the sidelobe cut (it passes without).
    """
    n = len(cands["scan"])
    out = {f"pass_{c}": np.zeros(n, bool) for c in CUT_ORDER}
    out.update(aspect_ratio=np.zeros(n), time_rms=np.zeros(n), instant_rms=np.zeros(n),
               opposite_snr=np.zeros(n), pol_fraction=np.zeros(n), pol_flag=np.zeros(n, bool))
    half_window = (int(round(cfg.sidelobe_window / np.median(np.diff(timestamps))))
                   if len(timestamps) > 1 else 0)
    near = near_known_source(cands["cluster_ra"], cands["cluster_dec"], known[0], known[1],
                             mask_radius)
    for c in range(n):
        dets, samps = per_detector_peaks(hits, c)
        speed = float(np.hypot(*drift[c]))
        direction = drift[c] / speed
        along_ext, across_ext, along = line_extents(xi[dets], eta[dets], direction)
        ok_time, r_drift, r_inst = time_order(timestamps[samps], along, speed, cfg.time_tolerance)
        out["aspect_ratio"][c] = (along_ext + pitch) / (across_ext + pitch)
        out["time_rms"][c], out["instant_rms"][c] = r_drift, r_inst
        out["pass_n_dets"][c] = len(dets) >= min_dets
        out["pass_aspect_ratio"][c] = out["aspect_ratio"][c] >= cfg.min_aspect_ratio
        out["pass_time_order"][c] = ok_time
        out["opposite_snr"][c] = opposite_peak(snr, dets, samps, half_window)
        out["pass_sidelobe"][c] = snr is None or (
            -out["opposite_snr"][c] <= cfg.max_opposite_ratio * cands["snr_max"][c])
        out["pass_known_source"][c] = not near[c]
        out["pol_fraction"][c] = dominant_orientation_fraction(gamma[dets])
        out["pol_flag"][c] = len(dets) >= min_dets and out["pol_fraction"][c] >= cfg.pol_fraction
    reasons = np.full(n, "", dtype=object)
    for cut in reversed(CUT_ORDER):
        reasons[~out[f"pass_{cut}"]] = cut
    out["cut_reason"] = reasons.astype(str) if n else np.zeros(0, str)
    out["passed"] = np.all([out[f"pass_{c}"] for c in CUT_ORDER], axis=0) if n else np.zeros(0, bool)
    return out


def cut_group_candidates(cands, hits, xi, eta, gamma, timestamps, drift, pitch, cfg: CutsConfig,
                         known, radius_by_band, snr=None, min_dets=FindConfig.min_dets):
    """:func:`apply_cuts` on every band of a group's candidates, each band with its own
    known-source mask radius (``radius_by_band``, radians); every ``transient_cuts`` column."""
    drift = np.asarray(drift).reshape(len(cands["bandpass"]), 2)

    def evaluate(band, sel, sub, sub_hits):
        return apply_cuts(sub, sub_hits, xi, eta, gamma, timestamps, drift[sel], pitch, cfg,
                          known, radius_by_band[band], snr, min_dets)
    return candidates.check(candidates.by_band(cands, hits, evaluate, "transient_cuts"),
                            "transient_cuts")
