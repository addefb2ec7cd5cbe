"""Matching detections to injected flares.

A detection matches a flare when it lies within ``max_offset`` (0.5') of the flare's position
and within ``max_dt`` (0.5 s) of a moment when the detection's group (observation, wafer,
band) crossed the source while it was flaring. Each crossing's moment is the peak of the
injected signal during that crossing: the maximum over samples of the flux times the beam at
the nearest detector. A slow flare is crossed in several scans; each crossing is a chance.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.table import Table
from scipy.spatial import cKDTree
from sotodlib import core

from so_transients.common.angles import ARCMIN, sky_separation
from so_transients.common.bands import fwhm_to_sigma, get_band
from so_transients.common.flare_model import active_window, flare_flux
from so_transients.common.pointing import angular_distance_xieta, boresight_quats, source_near



def crossing_times(timestamps, bore_q, det_xi, det_eta, flare, fwhm, min_gap=2.0, track=None):
    """Times (ctime) of the injected-signal peak in each crossing of ``flare`` by the detectors.

    ``flare``: a row with ``ra``, ``dec``, ``t_peak``, ``s_peak``, ``t_rise``, ``t_decay``,
    ``eta_rise``, ``eta_decay``; ``fwhm`` in radians. A crossing is a run of samples where the
    source is within one FWHM of some detector, runs closer than ``min_gap`` seconds merged.
    ``track``: the flare's ``(samples, xi, eta)`` from :func:`~so_transients.common.pointing.
    source_near` over its active window, with a reach of at least the detectors' footprint
    plus one FWHM, when the caller has it already (computed here otherwise).
    """
    centre = np.array([det_xi.mean(), det_eta.mean()])
    radius = np.hypot(det_xi - centre[0], det_eta - centre[1]).max() + fwhm
    if track is None:
        start, stop = active_window(flare["t_peak"], flare["t_rise"], flare["t_decay"])
        lo, hi = np.searchsorted(timestamps, [start, stop])
        near, xi, eta = source_near(bore_q[lo:hi], flare["ra"], flare["dec"], centre, radius)
        near = near + lo
    else:
        near, xi, eta = track
        inside = angular_distance_xieta(xi, eta, centre[0], centre[1]) < radius
        near, xi, eta = near[inside], xi[inside], eta[inside]
    if not len(near):
        return np.zeros(0)
    # the nearest detector in the (flat) focal plane, then its exact angular distance
    _, nearest = cKDTree(np.c_[det_xi, det_eta]).query(np.c_[xi, eta])
    dist = angular_distance_xieta(det_xi[nearest], det_eta[nearest], xi, eta)
    close = near[dist < fwhm]
    if not len(close):
        return np.zeros(0)
    t = timestamps[close]
    sigma = fwhm_to_sigma(fwhm)
    signal = flare_flux(t, flare["t_peak"], flare["s_peak"], flare["t_rise"],
                        flare["t_decay"], flare["eta_rise"], flare["eta_decay"]) \
        * np.exp(-0.5 * (dist[dist < fwhm] / sigma) ** 2)
    breaks = np.flatnonzero(np.diff(t) > min_gap) + 1
    times = []
    for run in np.split(np.arange(len(close)), breaks):
        if signal[run].max() > 0:
            times.append(t[run][np.argmax(signal[run])])
    return np.array(times)


def _rows_by_group(detections) -> dict:
    """{(obs_id, wafer_slot, bandpass): indices of the detections of that group}."""
    keys = zip(*(np.asarray(detections[k]).astype(str)
                 for k in ("obs_id", "wafer_slot", "bandpass")))
    groups = {}
    for i, key in enumerate(keys):
        groups.setdefault(key, []).append(i)
    return {key: np.asarray(rows) for key, rows in groups.items()}


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
    best_off = np.full(n, np.inf)
    if n:
        ra, dec, t = (np.asarray(out[k], float) for k in ("ra", "dec", "t_peak"))
        groups = _rows_by_group(out)
        # flares in table order and a strict "<": among equal offsets the first flare wins
        for fl in flares:
            off = sky_separation(ra, dec, float(fl["ra"]), float(fl["dec"]))
            for (obs_id, wafer, band), rows in groups.items():
                times = crossings.get((int(fl["source_id"]), obs_id, wafer, band))
                if band != str(fl["band"]) or times is None or not len(times):
                    continue
                dt = np.min(np.abs(np.asarray(times)[None, :] - t[rows, None]), axis=1)
                better = (off[rows] <= max_offset) & (dt <= max_dt) & (off[rows] < best_off[rows])
                hit = rows[better]
                source[hit], best_dt[hit], best_off[hit] = int(fl["source_id"]), dt[better], off[hit]
    best_off[source < 0] = np.nan
    out["source_id"] = source
    out["dt"] = best_dt * u.s
    out["offset"] = best_off * u.rad
    return out


def group_crossings(context_path, flares: Table, fwhm_by_band: dict) -> dict:
    """{(source_id, obs_id, wafer, band): crossing times} for every group of the dataset."""
    ctx = core.Context(str(context_path))
    out = {}
    for obs in ctx.obsdb.query():
        obs_id = obs["obs_id"]
        for detset in ctx.obsfiledb.get_detsets(obs_id):
            wafer, band = detset.split("_")
            aman = ctx.get_obs(obs_id, dets={"wafer_slot": wafer, "bandpass": band},
                               no_signal=True)
            q = boresight_quats(aman.timestamps, aman.boresight.az, aman.boresight.el,
                                aman.boresight.roll)
            for fl in flares[flares["band"] == band]:
                out[(int(fl["source_id"]), obs_id, wafer, band)] = crossing_times(
                    np.asarray(aman.timestamps), q, np.asarray(aman.focal_plane.xi),
                    np.asarray(aman.focal_plane.eta), fl, fwhm_by_band[band])
    return out


def compare_with_truth(dataset: Path, detections: Table):
    """``(matched, flares, crossings)``: the detections matched to the dataset's injected
    flares (:func:`match`), the flares (its ``truth/flares.ecsv``) and their crossing times
    per group (:func:`group_crossings`)."""
    flares = Table.read(dataset / "truth" / "flares.ecsv")
    fwhm = {b: get_band(b).fwhm for b in set(flares["band"])}
    crossings = group_crossings(dataset / "context.yaml", flares, fwhm)
    return match(detections, flares, crossings), flares, crossings
