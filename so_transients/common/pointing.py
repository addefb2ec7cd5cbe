"""Exact pointing for the samples that need it, with so3g quaternions.

Per-sample RA/Dec of every detector of an hour-long wafer is tens of GB. The simulator and the
detection steps need pointing only at a few places, so this module offers the three cheap
operations they use:

* :func:`boresight_quats` -- the boresight's celestial quaternion per sample (one per sample,
  computed by ``so3g.proj.CelestialSightLine``: precession, nutation, aberration and refraction);
* :func:`radec_of_samples` -- RA/Dec of chosen (detector, sample) pairs only;
* :func:`source_in_focal_plane` -- where a sky position falls in focal-plane coordinates
  (xi, eta) at chosen samples, from which the distance of every detector to it follows exactly
  (:func:`angular_distance_xieta`);
* :func:`source_near` -- the same, only for the samples where the source is near a detector
  group (coarse-to-fine: a source far from the group is never tracked sample by sample).

All angles are radians; times are ctime (seconds since 1970).
"""
from __future__ import annotations

import numpy as np
from so3g.proj import CelestialSightLine, quat

#: Site name understood by so3g for the SO LAT.
SITE = "so"


def boresight_sightline(timestamps, az, el, roll=None, weather="typical") -> CelestialSightLine:
    """so3g sight line of the boresight (celestial), from ctime and az/el/roll in radians."""
    timestamps = np.asarray(timestamps, dtype=np.float64)
    az = np.asarray(az, dtype=np.float64)
    el = np.asarray(el, dtype=np.float64)
    roll = None if roll is None else np.asarray(roll, dtype=np.float64)
    if not (timestamps.shape == az.shape == el.shape):
        raise ValueError("timestamps, az and el must have the same shape")
    return CelestialSightLine.az_el(timestamps, az, el, roll=roll, site=SITE, weather=weather)


def boresight_quats(timestamps, az, el, roll=None, weather="typical") -> np.ndarray:
    """Celestial quaternions of the boresight, shape (nsamps, 4), from ctime and az/el/roll."""
    return np.asarray(boresight_sightline(timestamps, az, el, roll, weather).Q)


def detector_quats(xi, eta, gamma=None):
    """so3g quaternions (G3VectorQuat) for focal-plane offsets xi, eta, gamma (radians)."""
    xi = np.atleast_1d(np.asarray(xi, dtype=np.float64))
    eta = np.atleast_1d(np.asarray(eta, dtype=np.float64))
    gamma = np.zeros_like(xi) if gamma is None else np.atleast_1d(np.asarray(gamma, np.float64))
    return quat.rotation_xieta(xi, eta, gamma)


def radec_of_samples(bore_q, xi, eta, det_index, samp_index):
    """RA, Dec (radians, RA in [0, 2pi)) of detector ``det_index[k]`` at sample ``samp_index[k]``.

    ``bore_q`` is the (nsamps, 4) array from :func:`boresight_quats`; ``xi``, ``eta`` are the
    focal-plane offsets of all detectors. Only the requested pairs are computed.
    """
    det_index = np.asarray(det_index, dtype=np.intp)
    samp_index = np.asarray(samp_index, dtype=np.intp)
    if det_index.shape != samp_index.shape:
        raise ValueError("det_index and samp_index must have the same shape")
    if det_index.size == 0:
        return np.zeros(0), np.zeros(0)
    q_bore = quat.G3VectorQuat(np.ascontiguousarray(bore_q[samp_index]))
    q_det = detector_quats(np.asarray(xi)[det_index], np.asarray(eta)[det_index])
    lon, lat, _ = quat.decompose_lonlat(q_bore * q_det)
    return np.mod(lon, 2 * np.pi), lat


def source_in_focal_plane(bore_q, ra, dec):
    """Focal-plane position (xi, eta) of a fixed sky position at every sample of ``bore_q``."""
    q_src = quat.rotation_lonlat(float(ra), float(dec))
    rel = ~quat.G3VectorQuat(np.ascontiguousarray(bore_q)) * q_src
    xi, eta, _ = quat.decompose_xieta(rel)
    return np.asarray(xi), np.asarray(eta)


def sources_in_focal_plane(bore_q, ra, dec):
    """Focal-plane positions (xi, eta) of the sky positions ``ra[i]``, ``dec[i]``, each at
    its own boresight ``bore_q[i]`` (one sample per position)."""
    q_src = quat.rotation_lonlat(np.asarray(ra, float), np.asarray(dec, float))
    rel = ~quat.G3VectorQuat(np.ascontiguousarray(bore_q)) * q_src
    xi, eta, _ = quat.decompose_xieta(rel)
    return np.asarray(xi), np.asarray(eta)


def source_near(bore_q, ra, dec, center, reach, stride=16):
    """Samples where a fixed sky position lies within ``reach`` (radians) of ``center`` (xi, eta)
    in the focal plane, and its (xi, eta) there: ``(samples, xi, eta)``.

    Exact, and equal to masking :func:`source_in_focal_plane` on every sample, but the track is
    first computed every ``stride`` samples; only the stretches between coarse samples closer
    than ``reach`` plus twice the largest coarse step (the most the source can move between
    them) are then computed sample by sample.
    """
    n = len(bore_q)
    if n == 0:
        return np.zeros(0, int), np.zeros(0), np.zeros(0)
    # the last sample is always a coarse point (repeated when it already is one: harmless)
    coarse = np.r_[np.arange(0, n, max(int(stride), 1)), n - 1]
    xi, eta = source_in_focal_plane(bore_q[coarse], ra, dec)
    step = float(np.max(angular_distance_xieta(xi[:-1], eta[:-1], xi[1:], eta[1:])))
    hit = angular_distance_xieta(xi, eta, center[0], center[1]) < reach + 2 * step
    spans = np.flatnonzero(hit[:-1] | hit[1:])
    mark = np.zeros(n + 1, int)
    np.add.at(mark, coarse[spans], 1)
    np.add.at(mark, coarse[spans + 1] + 1, -1)
    samples = np.flatnonzero(np.cumsum(mark[:-1]) > 0)
    if not len(samples):
        return samples, np.zeros(0), np.zeros(0)
    xi, eta = source_in_focal_plane(bore_q[samples], ra, dec)
    near = angular_distance_xieta(xi, eta, center[0], center[1]) < reach
    return samples[near], xi[near], eta[near]


def _unit_vectors(xi, eta):
    xi = np.asarray(xi, dtype=np.float64)
    eta = np.asarray(eta, dtype=np.float64)
    z = np.sqrt(np.clip(1.0 - xi**2 - eta**2, 0.0, None))
    return xi, eta, z


def angular_distance_xieta(xi1, eta1, xi2, eta2):
    """Exact angle (radians) between focal-plane directions (xi1, eta1) and (xi2, eta2).

    so3g's xi and eta are the transverse components of the unit vector in the boresight frame,
    so the chord between the two unit vectors gives the great-circle distance. Broadcasts.
    """
    x1, y1, z1 = _unit_vectors(xi1, eta1)
    x2, y2, z2 = _unit_vectors(xi2, eta2)
    chord = np.sqrt((x1 - x2) ** 2 + (y1 - y2) ** 2 + (z1 - z2) ** 2)
    return 2.0 * np.arcsin(np.clip(chord / 2.0, 0.0, 1.0))


def horizon_offsets(xi, eta, el):
    """Exact azimuth and elevation of detectors when the boresight is at az=0, elevation ``el``.

    For a constant-elevation scan with zero roll, a detector's azimuth is the boresight's plus the
    returned offset and its elevation is constant, so this gives every detector's horizon pointing
    at every sample without a per-sample computation. so3g's horizon frame uses lon = -az.
    """
    q_bore = quat.rotation_lonlat(0.0, float(el))
    lon, lat, _ = quat.decompose_lonlat(q_bore * detector_quats(xi, eta))
    return -np.asarray(lon), np.asarray(lat)


#: Field of an AxisManager where :func:`boresight_q` keeps the quaternions (never saved).
BORE_Q = "transient_bore_q"


def boresight_q(aman):
    """Celestial boresight quaternion of every sample of ``aman``, (nsamps, 4), from its
    standard ``timestamps`` and ``boresight`` (az, el, roll) fields, computed once per aman.

    This is one quaternion per sample (25 MB for an hour at 220 Hz), not per detector; it is
    kept in ``aman.transient_bore_q`` for the later steps.
    """
    if BORE_Q not in aman._fields:
        roll = aman.boresight.roll if "roll" in aman.boresight._fields else None
        q = boresight_quats(aman.timestamps, aman.boresight.az, aman.boresight.el, roll)
        aman.wrap(BORE_Q, q, [(0, "samps")])
    return np.asarray(aman[BORE_Q])
