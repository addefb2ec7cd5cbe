"""Which flares of a scan-end campaign peak near a turnaround, and were they found?

    python studies/scan_end_flares.py studies/configs/campaign_scan_ends_coherent.yaml \
        [-o OUTPUT] [--table docs/results/data/scan_ends/coherent_flares.ecsv]

After the campaign has run: for every injected flare of its ``results/flares.ecsv``, the time
from its peak to the nearest sample where the boresight is not at the scan speed (a
turnaround), from the boresight of the campaign's noise-only observation. Writes one row per
flare (band, t_r, S_p, peak ctime, that time, detected) to ``--table`` and prints, per
distance, how many flares peak that near a turnaround and how many of them were detected.
"""
import argparse
import sys
from pathlib import Path

import numpy as np
from astropy.table import Table
from sotodlib import core

from so_transients.campaign.config import load_campaign
from so_transients.campaign.provenance import commit, today
from so_transients.common.scan_geometry import constant_velocity

#: Distances (s) from a turnaround the summary counts flares within.
NEAR = (0.5, 1.0, 2.0)


def turnaround_times(folder) -> np.ndarray:
    """ctimes of the samples of the noise-only observation that are not at the scan speed."""
    aman = core.AxisManager.load(str(Path(folder) / "state.h5"), fields=["timestamps",
                                                                         "boresight"])
    t = np.asarray(aman.timestamps)
    scanning = constant_velocity(t, np.asarray(aman.boresight.az), np.asarray(aman.boresight.el))
    return t[~scanning]


def to_turnaround(t_peak, turning) -> np.ndarray:
    """Seconds from each of ``t_peak`` to the nearest of the sorted ``turning`` times."""
    i = np.clip(np.searchsorted(turning, t_peak), 1, len(turning) - 1)
    return np.minimum(np.abs(t_peak - turning[i - 1]), np.abs(turning[i] - t_peak))


def flare_table(cfg) -> Table:
    out = Path(cfg.output)
    flares = Table.read(out / "results" / "flares.ecsv")
    groups = sorted((out / "noise" / "groups").iterdir())
    turning = turnaround_times(groups[0])        # every group is the same observation
    t_peak = np.asarray(flares["t_peak"], float)
    table = Table({"band": flares["band"], "t_rise": flares["t_rise"],
                   "s_peak": flares["s_peak"], "t_peak": np.round(t_peak, 3),
                   "to_turnaround": np.round(to_turnaround(t_peak, turning), 3),
                   "detected": np.asarray(flares["detected"], bool)})
    table["t_peak"].description = "ctime of the flare's peak"
    table["to_turnaround"].unit = "s"
    table["to_turnaround"].description = "time from the flare's peak to the nearest turnaround"
    return table


def summary(table) -> list:
    """(label, flares, detected) within each of :data:`NEAR` seconds of a turnaround, then all."""
    rows = []
    for limit in NEAR:
        near = table["to_turnaround"] <= limit
        rows.append((f"within {limit:g} s", int(near.sum()), int(table["detected"][near].sum())))
    rows.append(("all", len(table), int(table["detected"].sum())))
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", help="the campaign's YAML")
    parser.add_argument("-o", "--out", help="its output folder (default: the config's)")
    parser.add_argument("--table", default="scan_end_flares.ecsv",
                        help="the per-flare table (ECSV; default: %(default)s)")
    args = parser.parse_args()
    cfg = load_campaign(args.config, {"output": args.out})
    table = flare_table(cfg)
    table.meta["comments"] = [f"{Path(sys.argv[0]).name} {args.config}: the flares of "
                              f"{cfg.output}/results/flares.ecsv",
                              f"this script at commit {commit()}, {today()}"]
    table.write(args.table, format="ascii.ecsv", overwrite=True)
    for label, n, found in summary(table):
        print(f"{label}: {found} of {n} detected")
    print(f"wrote {args.table}")


if __name__ == "__main__":
    main()
