"""sotodlib obs loader for simulated datasets, registered as ``obs_loader_type: so_transients``.

The Context calls :func:`load_sim_obs` with the ObsFileDb; it reads the HDF5 file of every
implicated detset (:mod:`so_transients.io.tod_file`) and returns an AxisManager with the standard
fields: ``signal`` (mJy), ``timestamps``, ``boresight`` (az, el, roll), plus an empty ``flags``
and ``iir_params`` so that sotodlib's preprocess ``Pipeline`` accepts it (the data carry no
readout filter to deconvolve). The Context adds ``det_info``, ``focal_plane`` and ``obs_info``,
and ``det_cal`` (``tau_eff``, s) when the simulation gave the detectors time constants.
"""
from __future__ import annotations

import os

import numpy as np
import sotodlib.io.metadata  # noqa: F401  registers sotodlib's HDF5 metadata loaders
from sotodlib import core

from so_transients.io.tod_file import read_tod

LOADER_NAME = "so_transients"


def _files_for(db, obs_id, dets):
    props = db.get_det_table(obs_id)
    if dets is None:
        detsets = sorted(set(props["dets:detset"]))
    else:
        wanted = set(np.asarray(dets, dtype=str))
        known = set(props["dets:readout_id"])
        missing = wanted - known
        if missing:
            raise ValueError(f"{obs_id}: {len(missing)} requested detectors are not in the "
                             f"ObsFileDb, e.g. {sorted(missing)[:3]}")
        detsets = sorted({ds for ds, rid in zip(props["dets:detset"], props["dets:readout_id"])
                          if rid in wanted})
    files = db.get_files(obs_id, detsets=detsets)
    prefix = db.prefix or ""
    return {ds: os.path.join(prefix, entries[0][0]) for ds, entries in files.items()}


def _read(obs_id, detset, path, dets, samples, no_signal):
    """:func:`read_tod`, with a file that cannot be read (missing, truncated, not HDF5, missing
    a dataset) reported as an OSError naming the observation, detset and file."""
    try:
        return read_tod(path, dets=dets, samples=samples, no_signal=bool(no_signal))
    except (OSError, KeyError, ValueError) as exc:
        raise OSError(f"{obs_id}: detset {detset}: cannot read TOD file {path}: "
                      f"{type(exc).__name__}: {exc}") from exc


def load_sim_obs(db, obs_id, dets=None, samples=None, prefix=None, no_signal=None, **kwargs):
    """Obsloader for so_transients simulations (see ``sotodlib.core.context.obsloader_template``)."""
    samples = (None, None) if samples is None else tuple(samples)
    files = _files_for(db, obs_id, dets)
    if not files:
        raise ValueError(f"{obs_id}: no TOD files found for the requested detectors")
    parts = [_read(obs_id, detset, path, dets, samples, no_signal)
             for detset, path in sorted(files.items())]
    names = np.concatenate([p["readout_id"] for p in parts])
    if dets is not None:
        order = {name: i for i, name in enumerate(names)}
        index = np.array([order[d] for d in dets], dtype=int)
    else:
        index = np.arange(len(names))
    head = parts[0]
    for p in parts[1:]:
        if not np.array_equal(p["timestamps"], head["timestamps"]):
            raise ValueError(f"{obs_id}: detsets have different timestamps and cannot be "
                             "loaded together")
    offset = samples[0] or 0
    aman = core.AxisManager(core.LabelAxis("dets", names[index]),
                            core.OffsetAxis("samps", len(head["timestamps"]), offset, obs_id))
    aman.wrap("timestamps", head["timestamps"], [(0, "samps")])
    bore = core.AxisManager(aman.samps)
    for name in ("az", "el", "roll"):
        bore.wrap(name, head[name], [(0, "samps")])
    aman.wrap("boresight", bore)
    if not no_signal:
        # one detset read in the requested order is used as read: no 2.7 GB copies per hour
        signal = (parts[0]["signal"] if len(parts) == 1
                  else np.concatenate([p["signal"] for p in parts]))
        if not np.array_equal(index, np.arange(len(names))):
            signal = signal[index]
        aman.wrap("signal", signal, [(0, "dets"), (1, "samps")])
    aman.wrap("flags", core.FlagManager.for_tod(aman, "dets", "samps"))
    aman.wrap("iir_params", core.AxisManager())
    return aman


def register():
    """Register the loader with sotodlib (idempotent)."""
    core.OBSLOADER_REGISTRY[LOADER_NAME] = load_sim_obs
