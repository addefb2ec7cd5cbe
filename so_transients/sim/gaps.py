"""Readout gaps: stretches of NaN on one detector at a time (dropped frames of one channel).

Each wafer-band has a Poisson number of them (``gaps.rate_per_hour``), each on a detector
drawn at random (dead ones included), at a uniformly random time, with a log-uniform duration.
"""
from __future__ import annotations

import numpy as np
from astropy import units as u
from astropy.table import Table

GAP_COLUMNS = ("obs_id", "readout_id", "ctime", "sample", "n_samples")


def draw_gaps(config, obs_id, readout_ids, timestamps, rng) -> Table:
    """Truth table of the NaN stretches of one detset: ``sample`` is the first NaN sample."""
    duration = timestamps[-1] - timestamps[0]
    count = rng.poisson(config.rate_per_hour * duration / 3600.0) if len(readout_ids) else 0
    rate = (len(timestamps) - 1) / duration if duration > 0 else 1.0
    dets = rng.integers(0, max(len(readout_ids), 1), count)
    starts = rng.integers(0, len(timestamps), count)
    lengths = np.maximum(1, np.round(np.exp(rng.uniform(*np.log(config.duration), count)) * rate)
                         ).astype(int)
    table = Table([np.array([obs_id] * count, dtype=str),
                   np.asarray(readout_ids)[dets] if count else np.zeros(0, str),
                   np.asarray(timestamps)[starts] if count else np.zeros(0),
                   starts.astype(int), lengths], names=GAP_COLUMNS)
    table["ctime"].unit = u.s
    return table


def add_gaps(tod, chunk_ids, gaps):
    """Set the samples of ``gaps`` that belong to detectors ``chunk_ids`` to NaN, in place."""
    where = {name: i for i, name in enumerate(chunk_ids)}
    for name, start, n in zip(gaps["readout_id"], gaps["sample"], gaps["n_samples"]):
        if name in where:
            tod[where[name], start:start + n] = np.nan
