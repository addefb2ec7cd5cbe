"""Reading transient results back: one astropy table from a preprocess archive or observation.

Two ways in, both giving the same table:

* :func:`archive_table` walks the archive's ManifestDb and loads each group's saved
  AxisManager on its own (how sotodlib stores per-group outputs);
* :func:`observation_table` loads a whole observation through the Context (all groups
  concatenated along ``dets``), which works because candidates are stored on the detector axis
  (:mod:`so_transients.slot_storage`).

The columns are those of :mod:`so_transients.candidates`, with their units (mJy for fluxes,
rad for positions, s of ctime for times) and descriptions, after ``obs_id``.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from astropy.table import Table, vstack
from sotodlib import core
from sotodlib.core.metadata import ManifestDb

from . import candidates
from .site import archive_index
from .slot_storage import unpack

#: Columns of every table read back, in order.
FIRST = ["obs_id"] + candidates.names(saved=True)


def amplitude(aman, dets=slice(None), lo=None, hi=None):
    """Amplitude timestream (signal units, mJy) of detectors ``dets``, samples ``lo:hi``: the
    S/N of ``transient_filter`` times each detector's ``sigma_amp``."""
    sigma = np.asarray(aman.transient_filter.sigma_amp, np.float32)[dets]
    return np.asarray(aman.transient_snr[dets, lo:hi]) * sigma[:, None]


def _empty_table() -> Table:
    return candidates.table({"obs_id": np.zeros(0, str), **candidates.empty()}, first=["obs_id"])


def proc_table(proc_aman, obs_id="", wafer_slot=None) -> Table:
    """Rows of every candidate stored in ``proc_aman`` (one group or several concatenated)."""
    parts = {name: unpack(proc_aman[name]) for name in candidates.STEPS
             if name in proc_aman._fields}
    base = parts.get("transient_find")
    if base is None or not len(base["cand_id"]):
        return _empty_table()
    rows = {}
    for name, part in parts.items():
        if not np.array_equal(part["cand_id"], base["cand_id"]):
            raise ValueError(f"{obs_id}: {name} is not aligned with transient_find")
        rows.update(part)
    rows.pop("det")
    n = len(base["cand_id"])
    rows["obs_id"] = np.full(n, obs_id)
    if "wafer_slot" not in rows:
        rows["wafer_slot"] = np.full(n, wafer_slot or "")
    return candidates.table(rows, first=["obs_id"])


def archive_entries(index_path):
    """(obs_id, group tags, absolute h5 filename, dataset) for every group in an archive."""
    index_path = Path(index_path)
    db = ManifestDb(str(index_path))
    out = []
    for entry in db.inspect():
        filename = entry["filename"]
        if not os.path.isabs(filename):
            filename = str(index_path.parent / filename)
        tags = {k.split(":", 1)[1]: v for k, v in entry.items() if k.startswith("dets:")}
        out.append((entry["obs:obs_id"], tags, filename, entry["dataset"]))
    return out


def archive_table(archive_or_config, detected_only=True) -> Table:
    """Every group of every observation in an archive, one group at a time, as one table."""
    tables = []
    for obs_id, tags, filename, dataset in archive_entries(archive_index(archive_or_config)):
        proc = core.AxisManager.load(filename, dataset)
        tables.append(proc_table(proc, obs_id, tags.get("wafer_slot")))
    table = vstack(tables) if tables else _empty_table()
    if not len(table):
        table = _empty_table()
    return table[np.asarray(table["detected"], bool)] if detected_only else table


def observation_table(context, obs_id, detected_only=True) -> Table:
    """The whole observation's candidates through the Context (all groups at once).

    ``context`` must have the preprocess archive among its metadata (as
    ``sotodlib.preprocess.preprocess_util.get_preprocess_context`` arranges).
    """
    meta = context.get_meta(obs_id)
    table = proc_table(meta.preprocess, obs_id)
    return table[np.asarray(table["detected"], bool)] if detected_only else table


def write_table(table: Table, path) -> Path:
    """Write ECSV or FITS, chosen by the file's suffix."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() in (".fits", ".fit"):
        out = table.copy()
        for name in out.colnames:
            if out[name].dtype.kind == "b":
                out[name] = out[name].astype(np.uint8)
        out.write(path, overwrite=True)
    else:
        table.write(path, format="ascii.ecsv", overwrite=True)
    return path
