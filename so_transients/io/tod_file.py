"""The on-disk TOD format of simulated observations: one HDF5 file per observation and detset.

Layout of a file::

    /readout_id        (ndet,)          detector names, in row order
    /timestamps        (nsamps,)  f8    ctime
    /boresight/az      (nsamps,)  f8    radians
    /boresight/el      (nsamps,)  f8    radians
    /boresight/roll    (nsamps,)  f8    radians
    /signal            (ndet, nsamps) f4, mJy (point-source calibrated), one HDF5 chunk per row

Attributes on the root: ``obs_id``, ``detset``, ``units`` (``mJy``). Rows are written detector
chunk by detector chunk, so an hour-long wafer never has to sit in memory at once, and reading
a subset of detectors reads only their rows.
"""
from __future__ import annotations

import h5py
import numpy as np

SIGNAL_UNITS = "mJy"


class TodWriter:
    """Create a TOD file and fill its signal rows chunk by chunk (use as a context manager)."""

    def __init__(self, path, obs_id, detset, readout_ids, timestamps, az, el, roll):
        self.file = h5py.File(path, "w")
        self.file.attrs.update(obs_id=obs_id, detset=detset, units=SIGNAL_UNITS)
        self.file["readout_id"] = np.asarray(readout_ids, dtype="S")
        self.file["timestamps"] = np.asarray(timestamps, dtype=np.float64)
        for name, value in (("az", az), ("el", el), ("roll", roll)):
            self.file[f"boresight/{name}"] = np.asarray(value, dtype=np.float64)
        nsamps = len(timestamps)
        self.signal = self.file.create_dataset(
            "signal", shape=(len(readout_ids), nsamps), dtype=np.float32,
            chunks=(1, min(nsamps, 1 << 20)))

    def write_rows(self, start, rows):
        self.signal[start:start + len(rows)] = rows

    def close(self):
        self.file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_tod(path, dets=None, samples=(None, None), no_signal=False):
    """Read a TOD file. ``dets``: readout ids to keep (file order kept); ``samples``: (start, stop).

    Returns a dict with ``readout_id``, ``timestamps``, ``az``, ``el``, ``roll`` and, unless
    ``no_signal``, ``signal`` (float32, mJy).
    """
    with h5py.File(path, "r") as f:
        names = f["readout_id"][()].astype(str)
        rows = np.arange(len(names))
        if dets is not None:
            rows = np.flatnonzero(np.isin(names, np.asarray(dets, dtype=str)))
        sl = slice(*samples)
        out = {"readout_id": names[rows], "timestamps": f["timestamps"][sl]}
        for name in ("az", "el", "roll"):
            out[name] = f[f"boresight/{name}"][sl]
        if not no_signal:
            if len(rows) == len(names):
                out["signal"] = f["signal"][:, sl]
            else:
                out["signal"] = f["signal"][rows, sl] if len(rows) else \
                    np.zeros((0, len(out["timestamps"])), np.float32)
        return out
