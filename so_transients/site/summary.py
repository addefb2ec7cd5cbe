"""A plain-text summary of a dataset, read back through sotodlib's Context like real data."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.table import Table
from sotodlib import core


def count_scans(az) -> int:
    """Number of sweeps in an azimuth timestream (one more than the number of turnarounds)."""
    velocity = np.diff(az)
    moving = velocity[velocity != 0]
    return int(np.count_nonzero(np.diff(np.sign(moving)) != 0) + 1) if len(moving) else 0


def dataset_summary(context_path) -> str:
    """Load every detset of every observation through the Context and describe it."""
    context_path = Path(context_path)
    ctx = core.Context(str(context_path))
    lines = [f"Dataset {context_path.parent}"]
    for obs in ctx.obsdb.query():
        obs_id = obs["obs_id"]
        lines.append(f"  {obs_id}: tube {obs['tube_slot']}, {obs['n_samples']} samples at "
                     f"{obs['sample_rate']:.0f} Hz ({obs['duration'] / 60:.1f} min)")
        for detset in ctx.obsfiledb.get_detsets(obs_id):
            wafer, band = detset.split("_")
            meta = ctx.get_meta(obs_id, dets={"wafer_slot": wafer, "bandpass": band})
            aman = ctx.get_obs(meta, no_signal=False)
            rms = float(np.median(np.std(aman.signal[:, :2000], axis=1)))
            lines.append(f"    {detset}: {aman.dets.count} detectors x {aman.samps.count} samples,"
                         f" {count_scans(aman.boresight.az)} scans, median rms of the first"
                         f" 2000 samples {rms:.0f} mJy")
    truth = context_path.parent / "truth" / "flares.ecsv"
    if truth.exists():
        flares = Table.read(truth)
        n = len(np.unique(flares["source_id"])) if len(flares) else 0
        lines.append(f"  injected flares: {n} ({len(flares)} flare-band rows)")
        for row in flares:
            lines.append(f"    #{row['source_id']} {row['band']}: S_p = {row['s_peak']:.0f} mJy, "
                         f"t_r = {row['t_rise']:.2f} s, t_p = {row['t_peak']:.2f}, "
                         f"ra = {np.degrees(row['ra']):.4f} deg, "
                         f"dec = {np.degrees(row['dec']):.4f} deg")
    return "\n".join(lines)
