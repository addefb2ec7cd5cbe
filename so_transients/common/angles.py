"""Angle units and the great-circle distance: defined once for the whole package.

Everything inside the package works in radians; these constants convert at the edges (config
keys with an ``_arcmin`` or ``_deg`` suffix, tables people read).
"""
from __future__ import annotations

import numpy as np

DEG = np.pi / 180
ARCMIN = DEG / 60
ARCSEC = ARCMIN / 60


def tangent_offsets(ra, dec, ra0, dec0):
    """Flat offsets (radians) of (ra, dec) from (ra0, dec0), shape (n, 2): east, north."""
    dra = np.angle(np.exp(1j * (ra - ra0)))
    return np.c_[dra * np.cos(dec0), dec - dec0]


def mean_direction(ra, dec):
    """RA (in (-pi, pi]) and Dec of the mean unit vector of points on the sphere."""
    vec = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)]).mean(axis=1)
    return np.arctan2(vec[1], vec[0]), np.arctan2(vec[2], np.hypot(vec[0], vec[1]))


def sky_separation(ra1, dec1, ra2, dec2):
    """Great-circle distance (radians) between (ra1, dec1) and (ra2, dec2); broadcasts."""
    cosd = np.sin(dec1) * np.sin(dec2) + np.cos(dec1) * np.cos(dec2) * np.cos(ra1 - ra2)
    return np.arccos(np.clip(cosd, -1, 1))
