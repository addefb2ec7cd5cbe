"""Readout jumps: from a random sample on, a detector's timestream is offset by a constant.

Jumps come from the readout (flux-ramp unlocks, 2 pi slips), so they are added after the
detector's response to the sky and are not filtered by its time constant. Each detector of an
observation has a Poisson number of them (``jumps.rate_per_hour``), at uniformly random samples,
with a log-uniform size of random sign, in mJy or in units of the detector's own white noise;
``jumps.fraction`` of the detectors, drawn at random, have ``jumps.count`` more (a uniform
integer in its range). Dead detectors jump like
the others: a jump is the readout's, not the detector's.
"""
from __future__ import annotations

import numpy as np
from astropy import units as u
from astropy.table import Table

JUMP_COLUMNS = ("obs_id", "readout_id", "ctime", "sample", "height")


def draw_jumps(config, obs_id, readout_ids, timestamps, white_rms, rng) -> Table:
    """Truth table of the jumps of one detset's detectors (``white_rms``: mJy per sample each).

    One row per jump: ``sample`` is the first sample offset by ``height`` (mJy).
    """
    rows = {name: [] for name in JUMP_COLUMNS}
    if config.enabled:
        mean = config.rate_per_hour * (timestamps[-1] - timestamps[0]) / 3600.0
        counts = rng.poisson(mean, len(readout_ids))
        if config.fraction > 0:
            more = rng.choice(len(readout_ids), int(round(config.fraction * len(readout_ids))),
                              replace=False)
            low, high = config.count
            counts[more] += rng.integers(low, high + 1, len(more)) if high > low else low
        for name, count, rms in zip(readout_ids, counts, white_rms):
            samples = np.sort(rng.integers(1, len(timestamps), count))
            size = np.exp(rng.uniform(*np.log(config.height), count))
            heights = size * rng.choice([-1.0, 1.0], count) * (rms if config.units == "white"
                                                               else 1.0)
            for samp, height in zip(samples, heights):
                for key, value in zip(JUMP_COLUMNS, (obs_id, name, timestamps[samp], samp,
                                                     height)):
                    rows[key].append(value)
    table = Table([np.array(rows[n], dtype=d) for n, d in
                   zip(JUMP_COLUMNS, (str, str, float, int, float))], names=JUMP_COLUMNS)
    table["ctime"].unit = u.s
    table["height"].unit = u.mJy
    return table


def add_jumps(tod, chunk_ids, jumps):
    """Add the steps of ``jumps`` that belong to detectors ``chunk_ids`` to ``tod`` in place."""
    where = {name: i for i, name in enumerate(chunk_ids)}
    mine = np.isin(jumps["readout_id"], list(where))
    for name, sample, height in zip(jumps["readout_id"][mine], jumps["sample"][mine],
                                    jumps["height"][mine]):
        tod[where[name], sample:] += np.float32(height)
