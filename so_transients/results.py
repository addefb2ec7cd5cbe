"""Reading transient results back: one astropy table from a preprocess archive or observation.

Two ways in, both giving the same table:

* :func:`archive_table` walks the archive's ManifestDb and loads each group's saved
  AxisManager on its own (how sotodlib stores per-group outputs);
* :func:`observation_table` loads a whole observation through the Context (all groups
  concatenated along ``dets``), which works because catalogues are stored on the detector axis
  (:mod:`so_transients.catalog`).

Columns carry units: mJy for fluxes, rad for positions, s (ctime) for times.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.table import Table, vstack
from sotodlib import core
from sotodlib.core.metadata import ManifestDb

from .catalog import unpack
from .site import archive_index

CATALOGS = ("transient_candidates", "transient_cuts", "transient_fit")
UNITS = {"ra": u.rad, "dec": u.rad, "ra_err": u.rad, "dec_err": u.rad, "flux": u.mJy,
         "flux_err": u.mJy, "offset": u.mJy, "offset_err": u.mJy, "t_peak": u.s,
         "t_median": u.s, "t_start": u.s, "t_stop": u.s, "cand_ra": u.rad, "cand_dec": u.rad}
FIRST = ["obs_id", "wafer_slot", "bandpass", "cand_id", "scan", "direction", "t_peak", "ra",
         "dec", "flux", "flux_err", "ra_err", "dec_err", "snr_fit", "offset", "offset_err",
         "n_dets", "n_samples", "chi2_red", "pol_flag", "detected", "cut_reason"]


def _empty_table() -> Table:
    dtypes = {"obs_id": "U64", "wafer_slot": "U8", "bandpass": "U8", "cut_reason": "U12",
              "pol_flag": bool, "detected": bool, "cand_id": int, "scan": int,
              "direction": int, "n_dets": int, "n_samples": int}
    table = Table([np.zeros(0, dtypes.get(c, float)) for c in FIRST], names=FIRST)
    for name, unit in UNITS.items():
        if name in table.colnames:
            table[name].unit = unit
    return table


def proc_table(proc_aman, obs_id="", wafer_slot=None) -> Table:
    """Rows of every candidate stored in ``proc_aman`` (one group or several concatenated)."""
    if "transient_candidates" not in proc_aman._fields:
        return _empty_table()
    parts = {name: unpack(proc_aman[name]) for name in CATALOGS if name in proc_aman._fields}
    base = parts["transient_candidates"]
    if not len(base["cand_id"]):
        return _empty_table()
    rows = {}
    for name, part in parts.items():
        if not np.array_equal(part["cand_id"], base["cand_id"]):
            raise ValueError(f"{obs_id}: {name} is not aligned with transient_candidates")
        rows.update(part)
    rows.pop("det")
    n = len(base["cand_id"])
    rows["obs_id"] = np.full(n, obs_id, dtype="U64")
    if "wafer_slot" not in rows:
        rows["wafer_slot"] = np.full(n, wafer_slot or "", dtype="U8")
    table = Table(rows)
    table.rename_columns(["ra", "dec"], ["cand_ra", "cand_dec"])
    fitted = np.asarray(table["fit_ok"], bool) if "fit_ok" in table.colnames else np.zeros(n, bool)
    for key in ("ra", "dec"):   # the fitted position when there is one, else the cluster mean
        source = table[f"fit_{key}"] if f"fit_{key}" in table.colnames else table[f"cand_{key}"]
        table[key] = np.where(fitted, source, table[f"cand_{key}"])
    for name, unit in UNITS.items():
        if name in table.colnames:
            table[name].unit = unit
    order = [c for c in FIRST if c in table.colnames]
    return table[order + [c for c in table.colnames if c not in order]]


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
