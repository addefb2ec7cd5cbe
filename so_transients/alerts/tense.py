"""Which alert tense an event gets: ``current`` for SO data, ``test`` for a simulated
dataset, ``injection`` for an event of a simulated dataset matched to a flare it injected.

An events table names the preprocess config it was made with (its ``provenance``); that
config's ``context_file`` lies in the dataset folder. The simulator writes
``sim_config.yaml`` into every dataset it makes, and ``truth/flares.ecsv`` (the injected
flares, radians and ctimes): a dataset with ``sim_config.yaml`` is a simulation, and an
event within ``injection_radius_arcmin`` of an injected flare while it was active
(:func:`so_transients.events.injections.match_events`) is an injection.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.table import Table

from so_transients.alerts.records import AlertsConfig
from so_transients.events.injections import match_events
from so_transients.common.angles import ARCMIN
from so_transients.site.pipeline import read_config

TENSES = ("current", "test", "injection")
SIM_MARKER = "sim_config.yaml"


def dataset_folder(events: Table, where) -> Path:
    """The dataset folder of an events table (from its provenance); ``where`` names the table
    in errors."""
    config = (events.meta.get("provenance") or {}).get("preprocess_config")
    if not config:
        raise ValueError(f"{where}: no provenance `preprocess_config`, so real data cannot be "
                         "told from a simulation (give the tense explicitly)")
    return Path(read_config(config)["context_file"]).resolve().parent


def event_tenses(events: Table, dataset, cfg: AlertsConfig) -> np.ndarray:
    """Each event's alert tense (see the module)."""
    dataset = Path(dataset)
    if not (dataset / SIM_MARKER).is_file():
        return np.full(len(events), "current", dtype="U9")
    tenses = np.full(len(events), "test", dtype="U9")
    truth = dataset / "truth" / "flares.ecsv"
    if truth.is_file() and len(events):
        flares = Table.read(truth)
        if len(flares):
            injected = match_events(events, flares, cfg.injection_radius_arcmin * ARCMIN,
                                    cfg.injection_pad_s).any(axis=1)
            tenses[injected] = "injection"
    return tenses
