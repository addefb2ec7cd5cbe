"""Cosmic-ray-like glitches: spikes that hit many detectors of a wafer at the same instant.

Each event has a time, a set of detectors (drawn at random across the wafer, both bands) and a
peak amplitude per detector; the spike decays exponentially with the detector time constant.
These are what the detection cuts must reject: many detectors, but all at one instant instead of
in the time order of a source drifting across the array.
"""
from __future__ import annotations

import numpy as np
from astropy import units as u
from astropy.table import Table

GLITCH_COLUMNS = ("glitch_id", "obs_id", "wafer_slot", "ctime", "n_dets", "amplitude_max",
                  "readout_ids", "amplitudes")


def draw_glitches(config, obs_id, wafer_slot, timestamps, readout_ids, rng) -> Table:
    """Truth table of glitch events on one wafer (``readout_ids``: all its detectors).

    ``readout_ids`` and ``amplitudes`` (mJy) of each event are comma-separated lists.
    """
    duration = timestamps[-1] - timestamps[0]
    n_events = rng.poisson(config.rate_per_hour * duration / 3600.0) if config.enabled else 0
    columns = {name: [] for name in GLITCH_COLUMNS}
    for k in range(n_events):
        n = min(int(rng.integers(config.n_dets[0], config.n_dets[1] + 1)), len(readout_ids))
        hit = np.sort(rng.choice(len(readout_ids), size=n, replace=False))
        amp = np.exp(rng.uniform(*np.log(config.amplitude_mjy), size=n))
        for name, value in zip(GLITCH_COLUMNS, (
                k, obs_id, wafer_slot, float(rng.uniform(timestamps[0], timestamps[-1])), n,
                float(amp.max()), ",".join(readout_ids[hit]), ",".join(f"{a:.3f}" for a in amp))):
            columns[name].append(value)
    dtypes = [int, str, str, float, int, float, str, str]
    table = Table([np.array(columns[n], dtype=d) for n, d in zip(GLITCH_COLUMNS, dtypes)],
                  names=GLITCH_COLUMNS)
    table["ctime"].unit = u.s
    table["amplitude_max"].unit = u.mJy
    return table


def add_glitches(tod, chunk_ids, timestamps, glitches, time_constant):
    """Add the spikes of ``glitches`` that hit detectors ``chunk_ids`` to ``tod`` in place."""
    dt = timestamps[1] - timestamps[0]
    span = int(np.ceil(10 * time_constant / dt)) + 1
    where = {name: i for i, name in enumerate(chunk_ids)}
    for row in glitches:
        start = int(np.searchsorted(timestamps, row["ctime"]))
        shape = np.exp(-(timestamps[start:start + span] - row["ctime"]) / time_constant)
        amps = [float(a) for a in row["amplitudes"].split(",")]
        for name, amp in zip(row["readout_ids"].split(","), amps):
            if name in where:
                tod[where[name], start:start + span] += (amp * shape).astype(tod.dtype)
