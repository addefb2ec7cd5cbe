"""Planet-like moving sources: constant flux, position moving steadily across the sky.

Each listed source is placed like a steady point source (``ra``/``dec`` in degrees, or where
``at_detector`` points at ``at_time``) at a reference time (``at_time``, else the start of the
first observation), and moves along a great circle at ``rate_arcmin_per_min``, heading there in
the direction ``direction_deg`` (position angle: 0 north, 90 east; default 90). ``flux_mjy`` is
one value for every band or ``{band: value}``. Its focal-plane track is computed sample by sample
(one quaternion per sample) and injected through the beam like any other source.
"""
from __future__ import annotations

import numpy as np
from astropy import units as u
from astropy.table import Table, vstack
from so3g.proj import quat

from so_transients.common.angles import ARCMIN
from so_transients.common.pointing import angular_distance_xieta
from so_transients.sim.sources import SourceCrossing, _explicit_position, empty_table

MOVING_COLUMNS = [("source_id", int, None), ("band", str, None), ("ra", float, u.rad),
                  ("dec", float, u.rad), ("t_ref", float, u.s), ("rate", float, u.arcmin / u.min),
                  ("direction", float, u.deg), ("flux", float, u.mJy)]
ENTRY_KEYS = {"ra", "dec", "at_detector", "at_time", "rate_arcmin_per_min", "direction_deg",
              "flux_mjy"}


def _flux(entry, band):
    flux = entry["flux_mjy"]
    return float(flux[band] if isinstance(flux, dict) else flux)


def draw_moving_sources(config, bands, ctx) -> Table:
    """Truth table of the listed moving sources (one row per source and band); ``ctx``: the
    :class:`~so_transients.sim.sources.PointingContext` of the first observation."""
    table = empty_table(MOVING_COLUMNS)
    for i, entry in enumerate(config.list):
        unknown = set(entry) - ENTRY_KEYS
        if unknown:
            raise ValueError(f"moving_sources: unknown keys {sorted(unknown)} in {entry}")
        ra, dec = _explicit_position(entry, ctx)
        t_ref = ctx.timestamps[0] + float(entry.get("at_time", 0.0))
        for band in bands:
            table.add_row(dict(source_id=i, band=band, ra=ra, dec=dec, t_ref=t_ref,
                               rate=float(entry["rate_arcmin_per_min"]),
                               direction=float(entry.get("direction_deg", 90.0)),
                               flux=_flux(entry, band)))
    return table


def position(src, timestamps):
    """RA, Dec (radians) of a moving source (a truth-table row) at ``timestamps``: along the
    great circle leaving (ra, dec) at position angle ``direction``, at a constant rate (which
    may be negative: before ``t_ref``)."""
    moved = src["rate"] * ARCMIN * (np.asarray(timestamps) - src["t_ref"]) / 60.0
    pa, dec0 = np.radians(src["direction"]), src["dec"]
    dec = np.arcsin(np.sin(dec0) * np.cos(moved) + np.cos(dec0) * np.sin(moved) * np.cos(pa))
    dra = np.arctan2(np.sin(pa) * np.sin(moved) * np.cos(dec0),
                     np.cos(moved) - np.sin(dec0) * np.sin(dec))
    return np.mod(src["ra"] + dra, 2 * np.pi), dec


def moving_crossings(timestamps, bore_q, sources, center, reach):
    """:class:`SourceCrossing` of each moving source (rows for one band) for the samples where it
    lies within ``reach`` (radians) of ``center`` (xi, eta) in the focal plane."""
    crossings = []
    for src in sources:
        ra, dec = position(src, timestamps)
        rel = ~quat.G3VectorQuat(np.ascontiguousarray(bore_q)) * quat.rotation_lonlat(ra, dec)
        xi, eta, _ = (np.asarray(a) for a in quat.decompose_xieta(rel))
        near = np.flatnonzero(angular_distance_xieta(xi, eta, center[0], center[1]) < reach)
        if len(near):
            crossings.append(SourceCrossing(near, xi[near], eta[near],
                                            np.full(len(near), float(src["flux"]))))
    return crossings


def track_table(sources, start, stop, step=1.0) -> Table:
    """Truth track of every moving source: its position every ``step`` s from ``start`` to
    ``stop`` (ctime)."""
    times = np.arange(start, stop + step / 2, step)
    tracks = []
    for src in sources[np.unique(sources["source_id"], return_index=True)[1]]:
        ra, dec = position(src, times)
        tracks.append(Table({"source_id": np.full(len(times), src["source_id"]),
                             "ctime": times * u.s, "ra": ra * u.rad, "dec": dec * u.rad}))
    return vstack(tracks)
