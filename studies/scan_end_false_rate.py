"""What searching up to the turnarounds costs in false detections, on a campaign's noise.

    python studies/scan_end_false_rate.py studies/configs/campaign_paper_mf.yaml [-o OUTPUT] [--buffer 3] \
        [--table docs/results/data/scan_ends/false_rate.ecsv]

After the campaign has run: for every prepared noise-only group in its output folder, runs the
campaign's search
steps on the noise-only S/N and on its sign-inverted copy twice: as configured (every sample at
the scan speed searched, ``turnaround_buffer: 0``), and with ``turnaround_buffer`` = ``--buffer``
seconds (3 s reproduces the earlier search, which skipped sotodlib's 1 s flag buffer and 2 s
more). The second search covers a subset of the first's samples on the same data, so the
difference is the cost of the scan ends. Prints, per band, the fitted candidates at S/N >= 3,
4 and 5 (5 = detections) per wafer-band-hour with Poisson errors, and writes the counts to
``--table`` (ECSV: band, wafer-band-hours, level, candidates now and with the buffer).
"""
import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np
from astropy.table import Table

from so_transients.campaign.config import load_campaign
from so_transients.campaign.provenance import stamp
from so_transients.campaign.noise import Group, GroupState
from so_transients.campaign.search_steps import SearchSteps

LEVELS = (3.0, 4.0, 5.0)


def with_buffer(search_steps, seconds):
    steps = copy.deepcopy(search_steps)
    for step in steps:
        if step["name"] == "transient_find":
            step["calc"] = {**(step.get("calc") or {}), "turnaround_buffer": float(seconds)}
    return steps


def count(group, folder, search_steps):
    """Fitted candidates above each level, on the noise-only S/N and its inverted copy."""
    state = GroupState.load(group, folder, search_steps)
    aman = state.aman
    aman.wrap("transient_snr", np.array(state.snr), [(0, "dets"), (1, "samps")])
    search = SearchSteps(search_steps, error_scale=state.error_scale)
    counts = np.zeros(len(LEVELS), int)
    for sign in (1, -1):
        aman.transient_snr[:] *= sign
        snr = np.asarray(search.run(aman, group.obs_id, fitted=True)["snr_fit"], float)
        counts += [int(np.sum(snr >= level)) for level in LEVELS]
    return counts


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", help="the campaign's YAML")
    parser.add_argument("-o", "--out", help="its output folder (default: the config's)")
    parser.add_argument("--buffer", type=float, default=3.0,
                        help="turnaround_buffer (s) of the comparison search")
    parser.add_argument("--table", default="scan_end_false_rate.ecsv",
                        help="the counts as an ECSV table (default: %(default)s)")
    args = parser.parse_args()
    cfg = load_campaign(args.config, {"output": args.out})
    _, search = cfg.pipeline_steps()
    rows = {}
    for folder in sorted((Path(cfg.output) / "noise" / "groups").iterdir()):
        obs_id, wafer, band = folder.name.rsplit("_", 2)
        group = Group(obs_id, wafer, band)
        hours = json.loads((folder / "info.json").read_text())["duration"] / 3600
        entry = rows.setdefault(band, dict(hours=0.0, now=np.zeros(3), before=np.zeros(3)))
        entry["hours"] += 2 * hours          # the data and their sign-inverted copy
        entry["now"] += count(group, folder, search)
        entry["before"] += count(group, folder, with_buffer(search, args.buffer))
        print(f"{folder.name}: now {entry['now']}, buffer {args.buffer:g} s {entry['before']}",
              flush=True)
    print(f"\nfitted candidates per wafer-band-hour (noise-only and sign-inverted data), "
          f"searched up to the turnarounds (now) vs. with a {args.buffer:g} s buffer")
    print("| band | wafer-band-hours | " + " | ".join(
        f"S/N >= {lvl:g}: now | buffer" for lvl in LEVELS) + " | ratio at >= 3 |")
    print("|---|---:|" + "---:|---:|" * len(LEVELS) + "---:|")
    for band, e in sorted(rows.items()):
        cells = [f"{n / e['hours']:.2f} ± {np.sqrt(max(n, 1)) / e['hours']:.2f} | "
                 f"{b / e['hours']:.2f} ± {np.sqrt(max(b, 1)) / e['hours']:.2f}"
                 for n, b in zip(e["now"], e["before"])]
        ratio = e["now"][0] / max(e["before"][0], 1)
        print(f"| {band} | {e['hours']:.1f} | " + " | ".join(cells) + f" | {ratio:.3f} |")
    write_table(rows, args)


def write_table(rows, args):
    """One row per band and S/N level: the wafer-band-hours searched and the fitted
    candidates at or above the level, searched up to the turnarounds and with the buffer."""
    table = Table(rows=[(band, e["hours"], level, int(now), int(before))
                        for band, e in sorted(rows.items())
                        for level, now, before in zip(LEVELS, e["now"], e["before"])],
                  names=("band", "wafer_band_hours", "snr_fit_min", "now", "buffer"))
    table.meta["comments"] = [
        f"{Path(sys.argv[0]).name} {args.config}, --buffer {args.buffer:g}",
        "noise-only data and their sign-inverted copy; now: turnaround_buffer 0 (as shipped), "
        f"buffer: turnaround_buffer {args.buffer:g} s",
        f"{stamp()}"]
    table.write(args.table, format="ascii.ecsv", overwrite=True)
    print(f"wrote {args.table}")


if __name__ == "__main__":
    main()
