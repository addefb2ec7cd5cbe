"""Flares and steady point sources: drawing them on the scanned sky and injecting them into TOD.

A source is seen by each detector through a Gaussian beam of the band's FWHM at the detector's
actual pointing. Pointing is computed only where it matters: for each source, the samples where
it is active (flares: eq. 1 of the paper is non-zero) are turned into the source's focal-plane
position (one quaternion per sample, :func:`so_transients.common.pointing.source_in_focal_plane`), and
the beam is evaluated only for samples where the source lies within reach of the detector group.

Random flares follow the paper's injection (section 2.4): the peak time is drawn uniformly from
the constant-velocity parts of the scans, and the position is where a randomly chosen simulated
detector points at that time (plus up to half a pixel pitch), so every flare is inside the
scanned footprint and crossed by a wafer near its peak. Campaigns can instead place it where a
random detector points at an independent random time (``placement="scan_area"``): anywhere in
the scanned area, so a fast flare's peak is usually not sampled.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from astropy import units as u
from astropy.table import Table

from so_transients.common.bands import CENTER_GHZ
from so_transients.common.flare_model import active_window, flare_flux
from so_transients.common.pointing import angular_distance_xieta, radec_of_samples, source_near

#: A flare's ``s_peak_mjy`` is its peak flux density at this frequency (f090's centre); each
#: band's is ``s_peak (nu / REFERENCE_GHZ)^spectral_index`` at the band's centre frequency.
REFERENCE_GHZ = CENTER_GHZ["f090"]

#: Beam is evaluated out to this many sigma.
BEAM_REACH_SIGMA = 6.0

#: Where :func:`draw_flares` puts random flares: at a detector's pointing at the peak time, or
#: at a detector's pointing at an independent random time (anywhere in the scanned area).
PLACEMENTS = ("detector_at_peak", "scan_area", "active_window")

FLARE_COLUMNS = [("source_id", int, None), ("band", str, None), ("ra", float, u.rad),
                 ("dec", float, u.rad), ("t_peak", float, u.s), ("s_peak", float, u.mJy),
                 ("t_rise", float, u.s), ("t_decay", float, u.s), ("eta_rise", float, None),
                 ("eta_decay", float, None), ("spectral_index", float, None)]
POINT_SOURCE_COLUMNS = [("source_id", int, None), ("band", str, None), ("ra", float, u.rad),
                        ("dec", float, u.rad), ("flux", float, u.mJy)]


def empty_table(columns) -> Table:
    """A zero-row table with the given (name, dtype, unit) columns."""
    return Table([np.zeros(0, dtype=dt if dt is not str else "U8") for _, dt, _ in columns],
                 names=[n for n, _, _ in columns],
                 units={n: un for n, _, un in columns if un is not None})


def _log_uniform(rng, low_high, size):
    low, high = low_high
    return np.exp(rng.uniform(np.log(low), np.log(high), size))


@dataclass
class PointingContext:
    """What is needed to draw positions: the time block's boresight and candidate detectors."""

    timestamps: np.ndarray
    bore_q: np.ndarray
    cv_mask: np.ndarray
    xi: np.ndarray
    eta: np.ndarray
    det_names: np.ndarray           # det_id of each detector
    pitch: float

    def detector_index(self, name) -> int:
        """Row of the detector named ``name``: a det_id (``w16_f090_p215A``) or a readout id
        (``w16_f090_0430``, what ``aman.dets`` lists)."""
        hits = np.flatnonzero(self.det_names == det_id_of(name))
        if not len(hits):
            raise ValueError(f"at_detector {name!r} is not a simulated detector (give a det_id "
                             "like w16_f090_p215A or a readout id like w16_f090_0430)")
        return int(hits[0])


def det_id_of(name: str) -> str:
    """The det_id of a simulated detector named by its det_id or its readout id: readout
    ``<wafer>_<band>_<NNNN>`` is pixel NNNN // 2, polarization A (even) or B (odd), det_id
    ``<wafer>_<band>_p<pixel:03d><pol>`` (as :func:`.focal_plane.wafer_detectors` names them)."""
    match = re.fullmatch(r"(\w+_f\d{3})_(\d{4})", str(name))
    if not match:
        return str(name)
    number = int(match.group(2))
    return f"{match.group(1)}_p{number // 2:03d}{'B' if number % 2 else 'A'}"



def _draw_position(rng, ctx: PointingContext, samp):
    det = rng.integers(len(ctx.xi))
    ra, dec = radec_of_samples(ctx.bore_q, ctx.xi, ctx.eta, [det], [samp])
    # jitter up to half a pixel pitch in a random direction
    r = 0.5 * ctx.pitch * np.sqrt(rng.uniform())
    phi = rng.uniform(0, 2 * np.pi)
    return float(np.mod(ra[0] + r * np.cos(phi) / np.cos(dec[0]), 2 * np.pi)), \
        float(dec[0] + r * np.sin(phi))


def _explicit_position(entry, ctx: PointingContext):
    if "ra" in entry and "dec" in entry:
        return np.radians(entry["ra"]), np.radians(entry["dec"])
    if "at_detector" in entry and "at_time" in entry:
        det = ctx.detector_index(entry["at_detector"])
        samp = int(np.argmin(np.abs(ctx.timestamps - ctx.timestamps[0] - entry["at_time"])))
        ra, dec = radec_of_samples(ctx.bore_q, ctx.xi, ctx.eta, [det], [samp])
        return float(ra[0]), float(dec[0])
    raise ValueError(f"a listed source needs ra/dec (deg) or at_detector/at_time: {entry}")


def _draw_durations(rng, config):
    """A random flare's rise and decay times (s)."""
    t_rise = float(_log_uniform(rng, config.t_rise, 1)[0])
    t_decay = t_rise if config.t_decay is None else float(_log_uniform(rng, config.t_decay, 1)[0])
    return t_rise, t_decay


def _nearest(timestamps, samples, t):
    """The one of ``samples`` whose time is nearest ``t``."""
    return int(samples[np.argmin(np.abs(timestamps[samples] - t))])


def draw_flares(config, bands, ctx: PointingContext, rng, placement="detector_at_peak") -> Table:
    """Truth table of flares (one row per flare and band), explicit ones first, then random.

    Random flares peak at a random constant-velocity sample; ``placement`` (:data:`PLACEMENTS`)
    puts them where a random detector points at that sample (``detector_at_peak``: the peak is
    sampled), at another, independent one (``scan_area``), or at the constant-velocity sample
    nearest a time uniform within the flare's active window (``active_window``: the array
    meets the flare at a random phase of its light curve), plus up to half a pixel pitch."""
    if placement not in PLACEMENTS:
        raise ValueError(f"flare placement {placement!r}: use one of {PLACEMENTS}")
    rows = []
    t0 = ctx.timestamps[0]
    for entry in config.list:
        ra, dec = _explicit_position(entry, ctx)
        t_rise = float(entry["t_rise"])
        rows.append(dict(ra=ra, dec=dec, t_peak=t0 + float(entry["t_peak"]),
                         s_peak=float(entry["s_peak_mjy"]), t_rise=t_rise,
                         t_decay=float(entry.get("t_decay", t_rise)),
                         eta_rise=float(entry.get("eta_rise", config.eta_rise)),
                         eta_decay=float(entry.get("eta_decay", config.eta_decay)),
                         spectral_index=float(entry.get("spectral_index",
                                                        config.spectral_index))))
    cv_samples = np.flatnonzero(ctx.cv_mask)
    for _ in range(config.n):
        samp = int(rng.choice(cv_samples))
        if placement == "active_window":
            t_rise, t_decay = _draw_durations(rng, config)
            at = _nearest(ctx.timestamps, cv_samples,
                          ctx.timestamps[samp] + rng.uniform(-t_rise, t_decay))
        else:
            at = samp if placement == "detector_at_peak" else int(rng.choice(cv_samples))
        ra, dec = _draw_position(rng, ctx, at)
        if placement != "active_window":
            t_rise, t_decay = _draw_durations(rng, config)
        rows.append(dict(ra=ra, dec=dec, t_peak=float(ctx.timestamps[samp]),
                         s_peak=float(_log_uniform(rng, config.s_peak_mjy, 1)[0]),
                         t_rise=t_rise, t_decay=t_decay,
                         eta_rise=config.eta_rise, eta_decay=config.eta_decay,
                         spectral_index=config.spectral_index))
    table = empty_table(FLARE_COLUMNS)
    for i, row in enumerate(rows):
        for band in bands:
            scale = (CENTER_GHZ[band] / REFERENCE_GHZ) ** row["spectral_index"]
            table.add_row(dict(row, source_id=i, band=band, s_peak=row["s_peak"] * scale))
    return table


def draw_point_sources(config, bands, ctx: PointingContext, rng) -> Table:
    """Truth table of steady point sources (one row per source and band)."""
    rows = []
    for entry in config.list:
        ra, dec = _explicit_position(entry, ctx)
        rows.append(dict(ra=ra, dec=dec, flux=float(entry["flux_mjy"])))
    cv_samples = np.flatnonzero(ctx.cv_mask)
    for _ in range(config.n):
        ra, dec = _draw_position(rng, ctx, int(rng.choice(cv_samples)))
        rows.append(dict(ra=ra, dec=dec, flux=float(_log_uniform(rng, config.flux_mjy, 1)[0])))
    table = empty_table(POINT_SOURCE_COLUMNS)
    for i, row in enumerate(rows):
        for band in bands:
            table.add_row(dict(row, source_id=i, band=band))
    return table


@dataclass
class SourceCrossing:
    """A source's focal-plane track and flux at the samples where it can touch a detector group."""

    samples: np.ndarray
    xi: np.ndarray
    eta: np.ndarray
    flux: np.ndarray


def source_crossings(timestamps, bore_q, sources, center, radius, sigma, steady=False):
    """Tracks of ``sources`` (rows of a truth table for one band) near a detector group.

    ``center`` (xi, eta) and ``radius`` describe the group's footprint in the focal plane;
    ``sigma`` is the beam's Gaussian sigma (radians). Returns a list of :class:`SourceCrossing`.
    """
    crossings = []
    reach = radius + BEAM_REACH_SIGMA * sigma
    for src in sources:
        if steady:
            lo, hi = 0, len(timestamps)
        else:
            start, stop = active_window(src["t_peak"], src["t_rise"], src["t_decay"])
            lo, hi = np.searchsorted(timestamps, [start, stop], side="left")
        if hi <= lo:
            continue
        samples, xi, eta = source_near(bore_q[lo:hi], src["ra"], src["dec"], center, reach)
        if not len(samples):
            continue
        samples = samples + lo
        if steady:
            flux = np.full(len(samples), float(src["flux"]))
        else:
            flux = flare_flux(timestamps[samples], src["t_peak"], src["s_peak"], src["t_rise"],
                              src["t_decay"], src["eta_rise"], src["eta_decay"])
        crossings.append(SourceCrossing(samples, xi, eta, flux))
    return crossings


def add_sources(tod, det_xi, det_eta, crossings, sigma):
    """Add the beam response of every crossing to ``tod`` (ndet, nsamps) in place, out to
    ``BEAM_REACH_SIGMA`` beam sigmas."""
    reach = BEAM_REACH_SIGMA * sigma
    for cross in crossings:
        # the flat focal-plane distance never exceeds the angle: it preselects the pairs
        flat2 = ((det_xi[:, None] - cross.xi[None, :]) ** 2
                 + (det_eta[:, None] - cross.eta[None, :]) ** 2)
        det, samp = np.nonzero(flat2 <= reach**2)
        dist = angular_distance_xieta(det_xi[det], det_eta[det], cross.xi[samp], cross.eta[samp])
        near = dist <= reach
        det, samp, dist = det[near], samp[near], dist[near]
        response = cross.flux[samp] * np.exp(-0.5 * (dist / sigma) ** 2)
        tod[det, cross.samples[samp]] += response.astype(tod.dtype)
