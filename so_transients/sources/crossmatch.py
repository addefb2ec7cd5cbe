"""Cross-match of measured positions and fluxes against catalogued sources.

As sotrplib's sifter does (simonsobs/sotrplib, ``sotrplib/sifter/crossmatch.py``, ``sift``,
with ``DefaultSifter``'s defaults in ``sotrplib/sifter/core.py``): the match radius grows with
the measured flux, ``radius_per_jy_arcmin`` (30') per Jy, at least ``min_radius_arcmin`` (1.5')
and at most ``max_radius_arcmin`` (2 deg), since a bright source's sidelobes and pointing
errors reach further; the nearest catalogued source within it is the match; a match whose
measured flux is more than ``flare_ratio`` (5, sotrplib's ``alert_on_flare``) times its
catalogued flux is a flare of that source. Solar-system objects are matched at their
position interpolated from the catalogue's ephemeris at the measurement's time.

Classes (``cat_class``):

* ``catalogued_flare``: a catalogued source, measured above ``flare_ratio`` x its flux;
* ``catalogued``: a catalogued source at about its catalogue flux (or with none catalogued);
* ``solar_system``: a solar-system object whose ephemeris covers the time, within the radius;
* ``new``: nothing catalogued within the radius.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from so_transients.common.angles import ARCMIN, sky_separation
from so_transients.common.sky_match import nearest_on_sky
from so_transients.common.step_config import positive, setting
from so_transients.sources.catalog import Catalogue, Ephemerides

CLASSES = ("catalogued_flare", "catalogued", "solar_system", "new")


@dataclass
class CrossmatchConfig:
    radius_per_jy_arcmin: float = setting(
        30.0, "arcmin", "match radius per Jy of measured flux (sotrplib's sifter)")
    min_radius_arcmin: float = setting(1.5, "arcmin", "match radius at least this (a faint source)")
    max_radius_arcmin: float = setting(120.0, "arcmin", "match radius at most this")
    flare_ratio: float = setting(
        5.0, "", "measured / catalogued flux above this: a catalogued source flaring")

    def __post_init__(self):
        positive("crossmatch", radius_per_jy_arcmin=self.radius_per_jy_arcmin,
                 min_radius_arcmin=self.min_radius_arcmin,
                 max_radius_arcmin=self.max_radius_arcmin, flare_ratio=self.flare_ratio)
        if self.max_radius_arcmin < self.min_radius_arcmin:
            raise ValueError(f"crossmatch: max_radius_arcmin {self.max_radius_arcmin} is below "
                             f"min_radius_arcmin {self.min_radius_arcmin}")


def match_radius(flux_mjy, cfg: CrossmatchConfig):
    """Match radius (radians) for measured fluxes (mJy; NaN: the minimum radius)."""
    per_jy = np.nan_to_num(np.asarray(flux_mjy, float), nan=0.0) / 1000.0 * cfg.radius_per_jy_arcmin
    return np.clip(per_jy, cfg.min_radius_arcmin, cfg.max_radius_arcmin) * ARCMIN


def _unit_vectors(ra, dec):
    return np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)])


def ephemeris_positions(ephem: Ephemerides, time):
    """``(sso_ids, names, ra, dec, flux_mjy)`` of each solar-system object at ``time``
    (ctimes): arrays (n_objects, n_times) in radians and mJy, NaN where the object's ephemeris
    points do not bracket the time. Positions are interpolated linearly on the unit sphere."""
    time = np.atleast_1d(np.asarray(time, float))
    ids = np.unique(ephem.sso_id)
    ra, dec, flux = (np.full((len(ids), len(time)), np.nan) for _ in range(3))
    names = np.empty(len(ids), object)
    for k, sso in enumerate(ids):
        mine = np.flatnonzero(ephem.sso_id == sso)
        mine = mine[np.argsort(ephem.time[mine])]
        names[k] = str(ephem.name[mine[0]])
        t = ephem.time[mine]
        inside = (time >= t[0]) & (time <= t[-1])
        if not inside.any():
            continue
        vec = _unit_vectors(ephem.ra[mine], ephem.dec[mine])
        at = np.stack([np.interp(time[inside], t, v) for v in vec])
        at /= np.linalg.norm(at, axis=0)
        ra[k, inside] = np.mod(np.arctan2(at[1], at[0]), 2 * np.pi)
        dec[k, inside] = np.arcsin(np.clip(at[2], -1, 1))
        flux[k, inside] = np.interp(time[inside], t, ephem.flux_mjy[mine])
    return ids, names.astype(str), ra, dec, flux


def _nearest(ra, dec, cat_ra, cat_dec):
    """Index and separation of the nearest of ``cat_*`` (n_cat, n) or (n_cat,) positions to
    each of the n positions (-1, inf where there is none)."""
    if not len(cat_ra):
        return np.full(len(ra), -1), np.full(len(ra), np.inf)
    cat_ra, cat_dec = np.asarray(cat_ra), np.asarray(cat_dec)
    if cat_ra.ndim == 1:    # fixed positions: astropy's k-d tree
        return nearest_on_sky(ra, dec, cat_ra, cat_dec)
    sep = np.nan_to_num(sky_separation(ra[None], dec[None], cat_ra, cat_dec), nan=np.inf)
    best = np.argmin(sep, axis=0)
    return best, sep[best, np.arange(len(ra))]


def crossmatch(ra, dec, flux_mjy, time, catalogue: Catalogue, ephem: Ephemerides | None,
               cfg: CrossmatchConfig) -> dict:
    """The nearest catalogued source within :func:`match_radius` of each measurement.

    ``ra``, ``dec`` in radians, ``flux_mjy`` the measured flux, ``time`` ctimes (for the
    solar-system objects). Returns columns (arrays of the measurements' length):
    ``catalogue`` (the catalogue's label, '' where nothing matched), ``cat_source_id``
    (socat's source_id or sso_id as a string, '' none), ``cat_source_name``, ``cat_ra`` and ``cat_dec``
    (degrees; a solar-system object's at ``time``), ``cat_separation`` (arcmin),
    ``cat_flux_ratio`` (measured / catalogued flux; NaN when the catalogue has no flux) and
    ``cat_class`` (see the module).
    """
    ra, dec = np.atleast_1d(np.asarray(ra, float)), np.atleast_1d(np.asarray(dec, float))
    flux = np.atleast_1d(np.asarray(flux_mjy, float))
    n = len(ra)
    radius = match_radius(flux, cfg)
    fixed, fixed_sep = _nearest(ra, dec, catalogue.ra, catalogue.dec)
    if ephem is not None and len(ephem):
        ids, names, e_ra, e_dec, e_flux = ephemeris_positions(ephem, time)
        moving, moving_sep = _nearest(ra, dec, e_ra, e_dec)
    else:
        ids = names = e_ra = e_dec = e_flux = None
        moving, moving_sep = np.full(n, -1), np.full(n, np.inf)
    out = dict(catalogue=np.full(n, "", object), cat_source_id=np.full(n, "", object),
               cat_source_name=np.full(n, "", object), cat_ra=np.full(n, np.nan),
               cat_dec=np.full(n, np.nan), cat_separation=np.full(n, np.nan),
               cat_flux_ratio=np.full(n, np.nan), cat_class=np.full(n, "new", object))
    with np.errstate(divide="ignore", invalid="ignore"):
        _fill(out, flux, radius, catalogue, (fixed, fixed_sep), (moving, moving_sep),
              (ids, names, e_ra, e_dec, e_flux), cfg)
    return {k: v.astype(str) if v.dtype == object else v for k, v in out.items()}


def _fill(out, flux, radius, catalogue, fixed_match, moving_match, objects, cfg):
    """Fill ``out`` (the columns of :func:`crossmatch`) measurement by measurement."""
    fixed, fixed_sep = fixed_match
    moving, moving_sep = moving_match
    ids, names, e_ra, e_dec, e_flux = objects
    for i in range(len(flux)):
        is_sso = moving_sep[i] <= radius[i] and moving_sep[i] < fixed_sep[i]
        if is_sso:
            k = moving[i]
            out["cat_source_id"][i], out["cat_source_name"][i] = ids[k], names[k]
            out["cat_ra"][i], out["cat_dec"][i] = np.degrees([e_ra[k, i], e_dec[k, i]])
            out["cat_separation"][i] = moving_sep[i] / ARCMIN
            out["cat_flux_ratio"][i] = flux[i] / e_flux[k, i]
            out["cat_class"][i] = "solar_system"
        elif fixed_sep[i] <= radius[i]:
            j = fixed[i]
            out["cat_source_id"][i] = catalogue.source_id[j]
            out["cat_source_name"][i] = catalogue.name[j]
            out["cat_ra"][i], out["cat_dec"][i] = np.degrees([catalogue.ra[j], catalogue.dec[j]])
            out["cat_separation"][i] = fixed_sep[i] / ARCMIN
            ratio = flux[i] / catalogue.flux_mjy[j]
            out["cat_flux_ratio"][i] = ratio
            out["cat_class"][i] = "catalogued_flare" if ratio > cfg.flare_ratio else "catalogued"
        else:
            continue
        out["catalogue"][i] = catalogue.label
