"""Matching detections to injected flares.

A detection matches a flare when it lies within ``max_offset`` (0.5') of the flare's position
and within ``max_dt`` (0.5 s) of a moment when the detection's group (observation, wafer,
band) crossed the source while it was flaring. Each crossing's moment is the peak of the
injected signal during that crossing: the maximum over samples of the flux times the beam at
the nearest detector. A slow flare is crossed in several scans; each crossing is a chance.
"""
from __future__ import annotations

import numpy as np
from astropy import units as u
from astropy.table import Table
from scipy.spatial import cKDTree

from .bands import fwhm_to_sigma
from .lightcurve import active_window, flare_flux
from .pointing import angular_distance_xieta, source_near

ARCMIN = np.pi / (180 * 60)


def crossing_times(timestamps, bore_q, det_xi, det_eta, flare, fwhm, min_gap=2.0):
    """Times (ctime) of the injected-signal peak in each crossing of ``flare`` by the detectors.

    ``flare``: a row with ``ra``, ``dec``, ``t_peak``, ``s_peak``, ``t_rise``, ``t_decay``,
    ``eta_rise``, ``eta_decay``; ``fwhm`` in radians. A crossing is a run of samples where the
    source is within one FWHM of some detector, runs closer than ``min_gap`` seconds merged.
    """
    start, stop = active_window(flare["t_peak"], flare["t_rise"], flare["t_decay"])
    lo, hi = np.searchsorted(timestamps, [start, stop])
    if hi <= lo:
        return np.zeros(0)
    centre = np.array([det_xi.mean(), det_eta.mean()])
    radius = np.hypot(det_xi - centre[0], det_eta - centre[1]).max() + fwhm
    near, xi, eta = source_near(bore_q[lo:hi], flare["ra"], flare["dec"], centre, radius)
    if not len(near):
        return np.zeros(0)
    # the nearest detector in the (flat) focal plane, then its exact angular distance
    _, nearest = cKDTree(np.c_[det_xi, det_eta]).query(np.c_[xi, eta])
    dist = angular_distance_xieta(det_xi[nearest], det_eta[nearest], xi, eta)
    close = near[dist < fwhm]
    if not len(close):
        return np.zeros(0)
    t = timestamps[lo:hi]
    sigma = fwhm_to_sigma(fwhm)
    signal = flare_flux(t[close], flare["t_peak"], flare["s_peak"], flare["t_rise"],
                        flare["t_decay"], flare["eta_rise"], flare["eta_decay"]) \
        * np.exp(-0.5 * (dist[dist < fwhm] / sigma) ** 2)
    breaks = np.flatnonzero(np.diff(t[close]) > min_gap) + 1
    times = []
    for run in np.split(np.arange(len(close)), breaks):
        if signal[run].max() > 0:
            times.append(t[close][run][np.argmax(signal[run])])
    return np.array(times)


def sky_separation(ra1, dec1, ra2, dec2):
    """Great-circle distance (radians)."""
    cosd = np.sin(dec1) * np.sin(dec2) + np.cos(dec1) * np.cos(dec2) * np.cos(ra1 - ra2)
    return np.arccos(np.clip(cosd, -1, 1))


def match(detections: Table, flares: Table, crossings: dict, max_dt=0.5,
          max_offset=0.5 * ARCMIN) -> Table:
    """Match each detection to at most one flare; returns ``detections`` with ``source_id``
    (-1: no match), ``dt`` (s, to the nearest crossing) and ``offset`` (rad) columns.

    ``crossings``: {(source_id, obs_id, wafer_slot, bandpass): array of crossing times}.
    """
    out = detections.copy()
    n = len(out)
    source = np.full(n, -1)
    best_dt = np.full(n, np.nan)
    best_off = np.full(n, np.nan)
    for i, det in enumerate(out):
        band_flares = flares[flares["band"] == det["bandpass"]]
        for fl in band_flares:
            off = sky_separation(float(det["ra"]), float(det["dec"]), fl["ra"], fl["dec"])
            times = crossings.get((int(fl["source_id"]), det["obs_id"], det["wafer_slot"],
                                   det["bandpass"]), np.zeros(0))
            if off > max_offset or not len(times):
                continue
            dt = np.min(np.abs(times - float(det["t_peak"])))
            if dt <= max_dt and (source[i] < 0 or off < best_off[i]):
                source[i], best_dt[i], best_off[i] = int(fl["source_id"]), dt, off
    out["source_id"] = source
    out["dt"] = best_dt * u.s
    out["offset"] = best_off * u.rad
    return out
