"""Scan geometry from standard SO fields, as plain functions on arrays.

The boresight's on-sky speed (the matched filter's template width is the beam over it), which
samples scan at constant speed, how fast a sky position drifts across the focal plane, and
the detector pitch. All angles in radians, times in ctime seconds.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from so_transients.common import pointing


def sample_rate(timestamps, where="") -> float:
    """Sample rate (Hz) of timestamps that increase with a regular step (the filter works in
    Fourier space); raises a ValueError naming ``where`` otherwise."""
    t = np.asarray(timestamps)
    dt = np.diff(t)
    if len(t) < 2 or not np.all(np.isfinite(t)):
        raise ValueError(f"{where} has too few or non-finite timestamps")
    if np.any(dt <= 0):
        raise ValueError(f"{where} timestamps are not strictly increasing "
                         f"({np.sum(dt <= 0)} steps <= 0)")
    step = np.median(dt)
    if dt.max() > 1.5 * step:
        raise ValueError(f"{where} timestamps have gaps (largest step {dt.max():.3f} s, "
                         f"nominal {step:.4f} s); fill or split the data")
    return 1.0 / step


def sample_speed(timestamps, az, el):
    """On-sky speed of the boresight at every sample (rad/s), from az and el."""
    t = np.asarray(timestamps)
    daz = np.gradient(np.unwrap(np.asarray(az)), t)
    return np.abs(daz) * np.cos(np.asarray(el))


def scan_direction(az) -> np.ndarray:
    """Scan direction per sample (int8): +1 where the azimuth increases (sotodlib's
    ``flags.right_scan``), -1 where it decreases (``flags.left_scan``)."""
    return np.where(np.gradient(np.unwrap(np.asarray(az, float))) >= 0, 1, -1).astype(np.int8)


def scan_speed(timestamps, az, el, where=""):
    """Median on-sky speed of the boresight (rad/s) while it scans."""
    speed = sample_speed(timestamps, az, el)
    moving = speed[speed > 0.5 * np.percentile(speed, 90)] if len(speed) else speed
    if not len(moving) or np.median(moving) <= 0:
        raise ValueError(f"{where}: the boresight does not scan")
    return float(np.median(moving))


def constant_velocity(timestamps, az, el, tolerance=0.01, where=""):
    """Samples where the boresight scans at its nominal on-sky speed (within ``tolerance``,
    a fraction of it): the constant-velocity part of every sweep, turnarounds excluded."""
    speed = sample_speed(timestamps, az, el)
    return np.abs(speed / scan_speed(timestamps, az, el, where) - 1) <= tolerance


def samples_in(timestamps, seconds) -> int:
    """Number of samples spanning ``seconds`` at the timestamps' mean rate."""
    t = np.asarray(timestamps)
    return int(round(seconds * (len(t) - 1) / (t[-1] - t[0])))


def drift_velocity(timestamps, bore_q, ra, dec, times, half_span=0.05):
    """Velocity (rad/s) of sky positions across the focal plane at the given times, (n, 2)."""
    t = np.asarray(timestamps)
    out = np.zeros((len(ra), 2))
    for k in range(len(ra)):
        i0, i1 = np.clip(np.searchsorted(t, [times[k] - half_span, times[k] + half_span]),
                         0, len(t) - 1)
        i1 = max(i1, min(i0 + 1, len(t) - 1))
        xi, eta = pointing.source_in_focal_plane(bore_q[[i0, i1]], ra[k], dec[k])
        out[k] = np.array([xi[1] - xi[0], eta[1] - eta[0]]) / max(t[i1] - t[i0], 1e-9)
    return out


def detector_pitch(xi, eta):
    """Median distance between neighbouring detector positions (radians)."""
    pos = np.unique(np.round(np.c_[xi, eta], 12), axis=0)
    if len(pos) < 2:
        return float(np.radians(1.5 / 60))
    dist, _ = cKDTree(pos).query(pos, k=2)
    return float(np.median(dist[:, 1]))
