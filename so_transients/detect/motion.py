"""Moving sources: detections of one group whose position drifts from scan to scan.

A planet, asteroid or satellite crosses the array like a transient in any one scan. Across the
scans of an observation it gives several detections whose positions move with time, where a
flare (or a steady source) stays put. Two kinds of hypothesis explain detections: a static
position (the detections within 5 position errors of one of them, then those within 3 errors
of their mean position) and a straight track
through two detections more than 5 errors apart that could be joined at ``max_rate`` (the
detections within 5 errors of it, then those within 3 errors of the line fitted to them).
A track counts only with motion its members' positions support
(:func:`motion_supported`: a flare's repeated crossings at one place and another flare
further away lie on a line, but two static positions explain them as well) and a
fitted rate (weighted least squares of the tangent-plane offsets against time) above
``min_rate`` and ``min_significance`` errors: the motion must be seen along the track, not
made by linking a static source with another one further away. The hypothesis explaining most detections is
taken first (a static one on ties), its members set aside, and so on: a steady source next
to a moving one stays static, and two detections alone are never flagged as moving, so one
noise detection near a flare cannot hide it.
"""
from __future__ import annotations

import numpy as np

from so_transients.common.angles import mean_direction, tangent_offsets



def _linear_rate(t, x, err):
    """Slope of x(t) and its error (weighted least squares)."""
    w = err ** -2.0
    t0 = np.sum(w * t) / np.sum(w)
    stt = np.sum(w * (t - t0) ** 2)
    if stt <= 0:
        return 0.0, np.inf
    return float(np.sum(w * (t - t0) * x) / stt), float(stt ** -0.5)


def motion_of(t, offsets, pos_err):
    """Rate (rad/s) of a set of detections at tangent-plane ``offsets`` and its error."""
    ve, se = _linear_rate(t, offsets[:, 0], pos_err)
    vn, sn = _linear_rate(t, offsets[:, 1], pos_err)
    rate = float(np.hypot(ve, vn))
    if rate == 0:
        return 0.0, float(min(se, sn))
    return rate, float(np.hypot(ve * se, vn * sn) / rate)


def _track_members(i, j, t, xy, pos_err, pool):
    """Detections of ``pool`` lying (within 5 errors) on the straight track through
    detections i and j."""
    velocity = (xy[j] - xy[i]) / (t[j] - t[i])
    predicted = xy[i] + velocity * (t[pool] - t[i])[:, None]
    miss = np.hypot(*(xy[pool] - predicted).T)
    return pool[miss <= 5 * np.hypot(pos_err[pool], pos_err[i])]


def _refined_members(members, t, xy, pos_err, pool, n_iter=3):
    """Members of ``pool`` within 3 errors of the straight line fitted (weighted least
    squares) to ``members``, iterated: a detection that only happens to lie within the two
    seeds' wide tolerance drops out once the line is fitted to all of them."""
    for _ in range(n_iter):
        w = pos_err[members] ** -2.0
        t0 = np.sum(w * t[members]) / np.sum(w)
        dt = t[members] - t0
        stt = np.sum(w * dt**2)
        if stt <= 0:
            return members
        x0 = np.sum(w[:, None] * xy[members], axis=0) / np.sum(w)
        v = np.sum((w * dt)[:, None] * xy[members], axis=0) / stt
        miss = np.hypot(*(xy[pool] - x0 - v * (t[pool] - t0)[:, None]).T)
        refined = pool[miss <= 3 * pos_err[pool]]
        if np.array_equal(refined, members):
            break
        members = refined
    return members


def _static_members(i, xy, pos_err, pool, n_iter=3):
    """Detections of ``pool`` within 5 errors of detection i's position, then those within 3
    errors of the members' weighted mean position (iterated), as for tracks."""
    miss = np.hypot(*(xy[pool] - xy[i]).T)
    members = pool[miss <= 5 * np.hypot(pos_err[pool], pos_err[i])]
    for _ in range(n_iter):
        w = pos_err[members] ** -2.0
        centre = np.sum(w[:, None] * xy[members], axis=0) / np.sum(w)
        refined = pool[np.hypot(*(xy[pool] - centre).T) <= 3 * pos_err[pool]]
        if np.array_equal(refined, members) or not len(refined):
            break
        members = refined
    return members


def _static_groups(xy, pos_err):
    """Detections at ``xy`` (errors ``pos_err``) grouped by position: taken in order of
    precision, each detection not within 5 combined errors of an earlier group's first
    member starts a new group (no chaining). Returns each detection's group."""
    first, group = [], np.zeros(len(xy), int)
    for i in np.argsort(pos_err, kind="stable"):
        near = [k for k, c in enumerate(first)
                if np.hypot(*(xy[i] - xy[c])) <= 5 * np.hypot(pos_err[i], pos_err[c])]
        if near:
            group[i] = near[0]
        else:
            group[i] = len(first)
            first.append(i)
    return group


def _chi2_about(xy, pos_err, model):
    return float(np.sum(np.sum((xy - model) ** 2, axis=1) / pos_err**2))


def motion_supported(t, xy, pos_err):
    """Whether detections at times ``t`` and tangent-plane positions ``xy`` (errors
    ``pos_err``) show motion: they occupy three or more distinct positions, or their two
    positions are fitted better by a straight track than by two static sources (a flare
    crossed twice at one place and another one further away are not)."""
    group = _static_groups(xy, pos_err)
    if group.max() >= 2:
        return True
    w = pos_err ** -2.0
    static = np.zeros_like(xy)
    for g in np.unique(group):
        sel = group == g
        static[sel] = np.sum(w[sel, None] * xy[sel], axis=0) / np.sum(w[sel])
    t0 = np.sum(w * t) / np.sum(w)
    dt = t - t0
    stt = np.sum(w * dt**2)
    x0 = np.sum(w[:, None] * xy, axis=0) / np.sum(w)
    v = np.sum((w * dt)[:, None] * xy, axis=0) / stt if stt > 0 else np.zeros(2)
    return _chi2_about(xy, pos_err, x0 + v * dt[:, None]) < _chi2_about(xy, pos_err, static)


def _local_rate(t, ra, dec, pos_err):
    """:func:`motion_of` in the tangent plane at the detections' own mean direction (a plane
    around a detection degrees away would distort their offsets by the change of cos(dec))."""
    return motion_of(t, tangent_offsets(ra, dec, *mean_direction(ra, dec)), pos_err)


def _best_explanation(t, ra, dec, xy, pos_err, pool, max_rate, min_rate, min_significance):
    """``(members, rate)`` of the hypothesis explaining most detections of ``pool``: a static
    position (rate 0; preferred on ties) or a significant straight track."""
    best, best_rate = np.zeros(0, int), 0.0
    for i in pool:
        members = _static_members(i, xy, pos_err, pool)
        if len(members) > len(best):
            best, best_rate = members, 0.0
    for i in pool:
        for j in pool:
            dt = t[j] - t[i]
            sep = np.hypot(*(xy[j] - xy[i]))
            err = np.hypot(pos_err[i], pos_err[j])
            if dt <= 0 or sep <= 5 * err or sep > max_rate * dt + 5 * err:
                continue
            members = _track_members(i, j, t, xy, pos_err, pool)
            if len(members) >= 3:
                members = _refined_members(members, t, xy, pos_err, pool)
            if len(members) < 3 or len(members) <= len(best) \
                    or not motion_supported(t[members], xy[members], pos_err[members]):
                continue
            rate, rate_err = _local_rate(t[members], ra[members], dec[members], pos_err[members])
            if rate > min_rate and rate > min_significance * rate_err:
                best, best_rate = members, rate
    return best, best_rate


def flag_moving(t, ra, dec, pos_err, max_rate, min_rate, min_significance=5.0):
    """``(moving, rate)`` per detection (rate in rad/s of the track it belongs to, NaN for
    detections on no track).

    ``t`` (s), ``ra``, ``dec``, ``pos_err`` (radians, one error per detection) of one band's
    detections; ``max_rate``/``min_rate`` in rad/s. Hypotheses are taken greedily: the one
    explaining most of the remaining detections first.
    """
    n = len(t)
    moving, rates = np.zeros(n, bool), np.full(n, np.nan)
    if n < 3:
        return moving, rates
    xy = tangent_offsets(ra, dec, ra[0], dec[0])
    pool = np.arange(n)
    while len(pool) >= 3:
        members, rate = _best_explanation(t, ra, dec, xy, pos_err, pool, max_rate, min_rate,
                                          min_significance)
        if len(members) < 2:
            break
        if rate > 0:
            moving[members], rates[members] = True, rate
        pool = np.setdiff1d(pool, members)
    return moving, rates
