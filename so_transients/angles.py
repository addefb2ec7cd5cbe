"""Angle units and the great-circle distance: defined once for the whole package.

Everything inside the package works in radians; these constants convert at the edges (config
keys with an ``_arcmin`` or ``_deg`` suffix, tables people read).
"""
from __future__ import annotations

import numpy as np

DEG = np.pi / 180
ARCMIN = DEG / 60
ARCSEC = ARCMIN / 60


def sky_separation(ra1, dec1, ra2, dec2):
    """Great-circle distance (radians) between (ra1, dec1) and (ra2, dec2); broadcasts."""
    cosd = np.sin(dec1) * np.sin(dec2) + np.cos(dec1) * np.cos(dec2) * np.cos(ra1 - ra2)
    return np.arccos(np.clip(cosd, -1, 1))
