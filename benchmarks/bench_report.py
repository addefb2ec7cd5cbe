"""Benchmark: the vetting site of a night's events (``so-transients report``).

    python benchmarks/bench_report.py                       # data/demo/events (make demo)
    python benchmarks/bench_report.py EVENTS --events 100   # any events folder, 100 events

A night of 100 events is made from an events folder's own events (their rows repeated under
new event ids and UUIDs, each with its cutouts, time streams and figure), so every page has
all it shows; then the site is written and timed. Prints the seconds in all and per event.
Target (issue "A vetting page"): 100 events in under a minute.
"""
import argparse
import shutil
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np
from astropy.table import Table, vstack

from so_transients.report.pages import build_report


def night(folder: Path, n_events: int, out: Path) -> Path:
    """An events folder of ``n_events`` made from ``folder``'s (files shared by copies)."""
    events = Table.read(folder / "events.ecsv")
    dets = Table.read(folder / "detections.ecsv")
    cuts = Table.read(folder / "cutouts.ecsv")
    if not len(events):
        sys.exit(f"{folder}: no events to repeat")
    for name in ("cutouts", "figures"):
        shutil.copytree(folder / name, out / name)
    parts = {"events": [], "detections": [], "cutouts": []}
    for k in range(n_events):
        source = k % len(events)
        eid = int(events["event_id"][source])
        row = events[source:source + 1].copy()
        row["event_id"] = k
        row["event_uuid"] = str(uuid.uuid5(uuid.UUID(str(row["event_uuid"][0])), str(k)))
        parts["events"].append(row)
        mine = dets[np.asarray(dets["event_id"]) == eid].copy()
        mine["event_id"] = k
        parts["detections"].append(mine)
        mine = cuts[np.asarray(cuts["event_id"]) == eid].copy()
        mine["event_id"] = k
        parts["cutouts"].append(mine)
        shutil.copyfile(folder / "figures" / f"event_{eid:04d}.png",
                        out / "figures" / f"event_{k:04d}.png")
    for name, tables in parts.items():
        vstack(tables, metadata_conflicts="silent").write(out / f"{name}.ecsv")
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("events", nargs="?", default="data/demo/events",
                   help="an events folder of `so-transients events` (default: make demo's)")
    p.add_argument("--events", dest="n_events", type=int, default=100)
    args = p.parse_args(argv)
    folder = Path(args.events)
    if not (folder / "cutouts.ecsv").is_file():
        sys.exit(f"{folder}: no cutouts.ecsv: run `make demo` (or `so-transients events`) "
                 "first")
    with tempfile.TemporaryDirectory(prefix="bench_report_") as tmp:
        made = night(folder, args.n_events, Path(tmp) / "events")
        t0 = time.perf_counter()
        build_report(made, Path(tmp) / "site", progress=False)
        seconds = time.perf_counter() - t0
    print(f"report of {args.n_events} events: {seconds:.1f} s "
          f"({seconds / args.n_events:.2f} s per event; target: 100 events under 60 s)")


if __name__ == "__main__":
    main()
