"""Candidate tables stored on the detector axis, so they survive sotodlib's concatenation.

sotodlib saves one preprocess AxisManager per group (wafer x band) and, when a whole
observation is loaded, concatenates the groups along ``dets``. A table with its own axis
would have a different length in each group and break that concatenation (or, with
``other_fields='first'``, silently keep only the first group). So candidate tables are stored
in *slots* attached to detectors: every field is a ``(dets, transient_slot)`` array, and
candidate ``k`` occupies one (detector, slot) cell -- the cell of the detector where it peaked
when free. ``occupied`` marks used cells (sotodlib adds its own ``valid`` ranges to saved
fields); the steps store each candidate's ``cand_id`` with its columns. Any concatenation of
groups along ``dets`` then still holds every candidate of every group, and
:func:`unpack` turns it back into rows.
"""
from __future__ import annotations

import logging

import numpy as np
from sotodlib import core

SLOT_AXIS = "transient_slot"
log = logging.getLogger(__name__)


def _assign_cells(preferred, n_dets, n_slots):
    """(row, slot) for each candidate: its preferred row when a slot is free, else the next."""
    load = np.zeros(n_dets, int)
    rows, slots = np.zeros(len(preferred), int), np.zeros(len(preferred), int)
    for k, row in enumerate(preferred):
        if load[row] >= n_slots:
            free = np.flatnonzero(load < n_slots)
            row = free[np.argmin(np.abs(free - row))]
        rows[k], slots[k] = row, load[row]
        load[row] += 1
    return rows, slots


def capacity(n_dets, n_slots):
    return n_dets * n_slots


def pack(axis_manager, columns: dict, preferred_rows, n_slots: int) -> core.AxisManager:
    """AxisManager (``dets`` of ``axis_manager`` x slots) holding one row per candidate.

    ``columns``: name -> array of length ncand (numbers, bools or strings); ``preferred_rows``:
    detector index where each candidate should sit. Raises if there are more candidates than
    cells (callers cap the number of candidates first).
    """
    n_dets = axis_manager.dets.count
    preferred = np.asarray(preferred_rows, int)
    ncand = len(preferred)
    if ncand > capacity(n_dets, n_slots):
        raise ValueError(f"{ncand} candidates do not fit in {n_dets} detectors x {n_slots} slots")
    rows, slots = _assign_cells(preferred, n_dets, n_slots)
    out = core.AxisManager(axis_manager.dets, core.IndexAxis(SLOT_AXIS, n_slots))
    occupied = np.zeros((n_dets, n_slots), bool)
    occupied[rows, slots] = True
    out.wrap("occupied", occupied, [(0, "dets"), (1, SLOT_AXIS)])
    for name, values in columns.items():
        values = np.asarray(values)
        if values.dtype.kind in "US":
            cells = np.zeros((n_dets, n_slots), dtype=f"U{max(values.dtype.itemsize // 4, 1)}")
        elif values.dtype.kind == "b":
            cells = np.zeros((n_dets, n_slots), bool)
        else:
            cells = np.zeros((n_dets, n_slots), dtype=np.result_type(values.dtype, np.float64)
                             if values.dtype.kind == "f" else values.dtype)
        if ncand:
            cells[rows, slots] = values
        out.wrap(name, cells, [(0, "dets"), (1, SLOT_AXIS)])
    return out


def unpack(packed: core.AxisManager, fields=None) -> dict:
    """Rows of a packed table (possibly several concatenated groups), ordered by
    detector then slot. Adds ``det`` (the readout id of the holding detector)."""
    occupied = np.asarray(packed.occupied, bool)
    rows, slots = np.nonzero(occupied)
    names = fields or [k for k in packed._fields
                       if packed._assignments[k] == ["dets", SLOT_AXIS] and k != "occupied"]
    out = {name: np.asarray(packed[name])[rows, slots] for name in names}
    out["det"] = np.asarray(packed.dets.vals)[rows]
    return out
