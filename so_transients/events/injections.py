"""Events matched to injected flares (a simulation's truth): which event is an injection.

Used by the alerts' tense (an event of a simulation at an injected flare is an injection) and
by the events check of the validation studies.
"""
from __future__ import annotations

import numpy as np
from astropy.table import Table

from so_transients.common.angles import sky_separation
from so_transients.common.flare_model import active_window


def match_events(events: Table, flares: Table, max_offset, pad) -> np.ndarray:
    """(n_events, n_flares) bool: the event lies within ``max_offset`` (radians) of the flare
    and its detections within the flare's active window (padded by ``pad`` s)."""
    ra, dec = np.radians(events["ra"]), np.radians(events["dec"])
    out = np.zeros((len(events), len(flares)), bool)
    for j, fl in enumerate(flares):
        start, stop = active_window(fl["t_peak"], fl["t_rise"], fl["t_decay"])
        near = sky_separation(ra, dec, fl["ra"], fl["dec"]) < max_offset
        overlap = (events["t_last"] >= start - pad) & (events["t_first"] <= stop + pad)
        out[:, j] = near & overlap
    return out
