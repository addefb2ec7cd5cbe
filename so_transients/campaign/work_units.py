"""One campaign work unit: the flares of one grid cell in one observation, injected and matched.

A unit is a plain dict (it crosses process and MPI boundaries) naming the cell, the observation,
its prepared groups, the search steps and the options; :func:`run_unit` writes its results
as two ECSV files under ``<output>/units/`` and returns a short summary. The flares file is
written last and atomically: its presence marks the unit done, which is what resuming checks.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.table import Table, vstack

from so_transients.common.flare_model import flare_flux
from so_transients.common.angles import ARCMIN
from so_transients.campaign.matching import match
from so_transients.sim.simulate import rng_for
from so_transients.campaign.config import Cell, Injection
from so_transients.campaign.flare_injection import draw_cell_flares, inject_flare
from so_transients.campaign.noise import Group, GroupState
from so_transients.campaign.search_steps import SearchSteps, stack

_STATES: dict = {}     # per process: prepared groups already opened


def _state(group, folder, search_steps):
    key = str(folder)
    if key not in _STATES:
        _STATES[key] = GroupState.load(group, folder, search_steps)
    return _STATES[key]


def unit_paths(output, cell: Cell, obs_id):
    base = Path(output) / "units" / f"{cell.label}__{obs_id}"
    return Path(f"{base}.flares.ecsv"), Path(f"{base}.detections.ecsv")


def unit_done(output, cell, obs_id, digest) -> bool:
    path = unit_paths(output, cell, obs_id)[0]
    if not path.exists():
        return False
    return Table.read(path).meta.get("config_digest") == digest


def _write(table, path):
    tmp = path.with_name(path.name + ".tmp")
    table.write(tmp, format="ascii.ecsv", overwrite=True)
    os.replace(tmp, path)


def _annotate(matched, flare):
    """Truth at each matched detection: flux then, peak flux, and which is nearest the peak."""
    t = np.asarray(matched["t_peak"], float)
    matched["flux_true"] = flare_flux(t, flare["t_peak"], flare["s_peak"], flare["t_rise"],
                                      flare["t_decay"], flare["eta_rise"],
                                      flare["eta_decay"]) * u.mJy
    matched["s_peak"] = np.full(len(matched), float(flare["s_peak"])) * u.mJy
    matched["t_rise"] = np.full(len(matched), float(flare["t_rise"])) * u.s
    nearest = np.zeros(len(matched), bool)
    if len(matched):
        nearest[np.argmin(np.abs(t - flare["t_peak"]))] = True
    matched["nearest_peak"] = nearest
    return matched


def search_flares(states, flares, options, max_dt, max_offset):
    """Inject each flare alone into the prepared ``states``, search and match it; returns
    ``flares`` with per-flare counts and ``detected``, and the matched detections."""
    flares = flares.copy()
    searches = [SearchSteps(s.search_steps, error_scale=s.error_scale) for s in states]
    columns = {k: np.zeros(len(flares), int) for k in ("n_crossings", "n_searched", "n_skipped",
                                                       "n_detections")}
    found = []
    for i, flare in enumerate(flares):
        crossings, tables = {}, []
        for state, search in zip(states, searches):
            res = inject_flare(state, flare, search, options)
            g = state.group
            crossings[(int(flare["source_id"]), g.obs_id, g.wafer, g.band)] = res.times
            columns["n_crossings"][i] += len(res.times)
            columns["n_searched"][i] += res.n_searched
            columns["n_skipped"][i] += res.n_skipped
            if len(res.detections):
                tables.append(res.detections)
        if tables:
            matched = match(stack(tables), flares[i:i + 1], crossings, max_dt, max_offset)
            matched = matched[matched["source_id"] >= 0]
            columns["n_detections"][i] = len(matched)
            if len(matched):
                found.append(_annotate(matched, flare))
    for name, values in columns.items():
        flares[name] = values
    flares["detected"] = flares["n_detections"] > 0
    return flares, (vstack(found) if found else Table())


def run_unit(spec: dict) -> dict:
    """Inject, search and match the flares of one unit (see the module doc)."""
    cell = Cell(**spec["cell"])
    states = [_state(Group(*g), folder, spec["search_steps"]) for g, folder in spec["groups"]]
    rng = rng_for(spec["seed"], "campaign", cell.label, spec["obs_id"])
    options = Injection(**spec["injection"])
    flares = draw_cell_flares(cell, spec["n"], states, rng, options.placement,
                              options.flare_eta)
    flares["source_id"] += spec["first_id"]
    flares, detections = search_flares(states, flares, options,
                                       spec["max_dt"], spec["max_offset_arcmin"] * ARCMIN)
    flares["obs_id"] = spec["obs_id"]
    meta = {"config_digest": spec["digest"], "cell": cell.label, "obs_id": spec["obs_id"]}
    flares.meta.update(meta)
    detections.meta.update(meta)
    flares_path, det_path = unit_paths(spec["output"], cell, spec["obs_id"])
    flares_path.parent.mkdir(parents=True, exist_ok=True)
    _write(detections, det_path)
    _write(flares, flares_path)
    return {"cell": cell.label, "obs_id": spec["obs_id"], "n": len(flares),
            "detected": int(flares["detected"].sum())}
