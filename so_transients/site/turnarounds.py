"""Observations too short for the turnaround flags of a site preprocess config.

sotodlib's ``flag_turnarounds`` step with ``method: scanspeed`` (the method of
``configs/preprocess_transients.yaml``, and sotodlib's default) finds the turnarounds as peaks
of a matched filter on the azimuth speed and takes the mean distance between them: an
observation with fewer than two turnarounds (on the simulator's 90 s sweeps: shorter than
177.5 s) stops inside it with ``ValueError: cannot convert float NaN to integer``.
:func:`short_observations` finds such observations before the site pipeline runs, from each
observation's boresight (one detector, no signal), and names each with its duration.
"""
from __future__ import annotations

import logging

import numpy as np
from sotodlib import core

from so_transients.site.pipeline import read_config
from so_transients.site.summary import count_scans

log = logging.getLogger(__name__)

#: Turnarounds sotodlib's flag_turnarounds (``method: scanspeed``) needs in an observation.
MIN_TURNAROUNDS = 2


def count_turnarounds(az) -> int:
    """Azimuth reversals of a boresight timestream: :func:`count_scans` - 1 over the samples
    moving at more than half the median speed, so that encoder noise while the boresight
    stands still at a turnaround does not add reversals (0 without motion)."""
    az = np.asarray(az, dtype=float)
    speed = np.abs(np.diff(az))
    if not len(speed) or not speed.any():
        return 0
    moving = np.flatnonzero(speed > 0.5 * np.median(speed))
    return max(count_scans(az[moving]) - 1, 0)


def scanspeed_steps(process_pipe) -> list:
    """Indices of the ``flag_turnarounds`` entries of ``process_pipe`` that run the
    ``scanspeed`` method (the default when a section names no method) in their ``process`` or
    ``calc`` section."""
    out = []
    for i, step in enumerate(process_pipe):
        if step.get("name") != "flag_turnarounds":
            continue
        sections = [step.get(s) for s in ("process", "calc") if step.get(s) is not None]
        if any((s if isinstance(s, dict) else {}).get("method", "scanspeed") == "scanspeed"
               for s in sections):
            out.append(i)
    return out


def observation_turnarounds(context, obs_id) -> tuple:
    """``(duration in s, turnarounds)`` of observation ``obs_id`` of a sotodlib ``Context``,
    from its timestamps and boresight azimuth (read with one detector and no signal)."""
    det_info = context.get_det_info(obs_id)
    if not len(det_info):
        raise ValueError(f"{obs_id}: no detectors in the dataset's det_info")
    first = {}                     # the first detector of each detset: one file each
    for detset, readout_id in zip(det_info["detset"], det_info["readout_id"]):
        first.setdefault(detset, readout_id)
    errors = []
    for detset, readout_id in first.items():
        try:
            aman = context.get_obs(obs_id, dets=[readout_id], no_signal=True)
        except (OSError, ValueError, KeyError) as exc:   # that detset's file: its groups fail
            errors.append(f"{detset}: {exc}")
            continue
        t = np.asarray(aman.timestamps)
        return float(t[-1] - t[0]), count_turnarounds(aman.boresight.az)
    raise OSError(f"{obs_id}: no detset can be read ({'; '.join(errors)})")


def short_observations(config_path, selection=None) -> list:
    """One line per observation of a site preprocess config's dataset (of those
    ``selection`` takes) that its ``flag_turnarounds`` step (``method: scanspeed``) cannot
    flag: fewer than :data:`MIN_TURNAROUNDS` turnarounds. Each names the observation, its
    duration and its turnarounds; [] when the config runs no such step. An observation whose
    files cannot be read is left to the site pipeline, where its groups fail, named."""
    cfg = read_config(config_path)
    if not scanspeed_steps(cfg.get("process_pipe") or []):
        return []
    context = core.Context(cfg["context_file"])
    chosen = None if selection is None or selection.everything else selection.obs_ids(context)
    lines = []
    for obs in context.obsdb.query():
        if chosen is not None and obs["obs_id"] not in chosen:
            continue
        try:
            duration, n = observation_turnarounds(context, obs["obs_id"])
        except OSError as exc:
            log.warning("%s: cannot check its turnarounds: %s", config_path, exc)
            continue
        if n < MIN_TURNAROUNDS:
            lines.append(f"{obs['obs_id']}: {duration:.0f} s with {n} turnaround(s), too short "
                         f"for flag_turnarounds (method scanspeed) of {config_path}: it needs "
                         f"{MIN_TURNAROUNDS} complete turnarounds and stops with 'cannot convert "
                         "float NaN to integer' with fewer; leave the observation out, or remove "
                         "that step (no transient step reads its flags)")
    return lines
