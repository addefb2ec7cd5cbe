"""``so-transients alerts EVENTS_FOLDER -o OUT``: alerts for the events of an events folder.

Reads ``events.ecsv`` (and ``lightcurve_fits.ecsv`` for the flare durations) written by
``so-transients events``, the alerts already in ``OUT``, and writes one JSON file per new
alert (``<id>-<record_number>.json``, validated against ``alert.schema.json``), with
``--voevent`` also its VOEvent 2.0 XML (``.xml``) (see :mod:`so_transients.alerts.records`
for what is alerted, updated and retracted, :mod:`so_transients.alerts.tense` for the tense).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from so_transients.alerts.records import (
    CUTOUT_FILES, AlertsConfig, file_name, plan_alerts, read_alerts
)
from so_transients.alerts.tense import TENSES, dataset_folder, event_tenses
from so_transients.alerts.voevent import to_voevent
from so_transients.common.tables import read_table


def get_parser(parser=None):
    if parser is None:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    defaults = AlertsConfig()
    parser.add_argument("events", help="events folder (events.ecsv of `so-transients events`)")
    parser.add_argument("-o", "--out", required=True,
                        help="alerts folder: earlier alerts are read from it, new ones added")
    parser.add_argument("--min-snr", type=float, default=defaults.min_snr,
                        help=f"alert events with at least this S/N (default {defaults.min_snr})")
    parser.add_argument("--max-far-hz", type=float, default=defaults.max_far_hz,
                        help="and an instrument-level false-alarm rate at most this (Hz; "
                             "default: no cut)")
    parser.add_argument("--wafer-bands", type=int, default=defaults.wafer_bands,
                        help="wafer-bands searched at once: far per wafer-band times this is "
                             f"the instrument's far the alerts carry (default {defaults.wafer_bands}, "
                             "the LAT)")
    parser.add_argument("--voevent", action="store_true", help="also write VOEvent 2.0 XML")
    parser.add_argument("--tense", choices=TENSES, default=None,
                        help="every alert's tense (default: from the events' dataset)")
    return parser


def write_alerts(records, out: Path, voevent=False) -> list:
    """One JSON file per record (and its VOEvent XML); returns the JSON paths."""
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for record in records:
        path = out / file_name(record)
        if path.exists():
            raise ValueError(f"{path}: an alert of that id and number exists already")
        path.write_text(json.dumps(record, indent=1) + "\n")
        if voevent:
            path.with_suffix(".xml").write_text(to_voevent(record))
        paths.append(path)
    return paths


def run_alerts(events_folder, out, cfg: AlertsConfig, voevent=False, tense=None) -> list:
    """Plan and write the alerts of an events folder; returns the records written."""
    folder = Path(events_folder)
    events_path = folder / "events.ecsv"
    if not events_path.is_file():
        raise ValueError(f"{folder}: no events.ecsv (run `so-transients events` first)")
    events = read_table(events_path)
    missing = [c for c in ("event_uuid", "source_uuid") if c not in events.colnames]
    if missing:
        raise ValueError(f"{events_path}: no {', '.join(missing)} (written by an older "
                         "so_transients): run `so-transients events` again")
    fits_path = folder / "lightcurve_fits.ecsv"
    fits = read_table(fits_path) if fits_path.is_file() else None
    cutouts_path = folder / "cutouts.ecsv"
    if cutouts_path.is_file():
        cutouts = read_table(cutouts_path)
        files = {}
        for eid, name in zip(cutouts["event_id"], cutouts["file"]):
            files.setdefault(int(eid), []).append(str(name))
        events[CUTOUT_FILES] = [",".join(files.get(int(e), [])) for e in events["event_id"]]
    if tense is None:
        tenses = event_tenses(events, dataset_folder(events, events_path), cfg)
    else:
        tenses = [tense] * len(events)
    covered = (events.meta.get("provenance") or {}).get("obs_ids", [])
    records = plan_alerts(events, fits, tenses, read_alerts(out), covered, cfg)
    write_alerts(records, Path(out), voevent)
    return records


def main(args) -> int:
    """Exit status 0; a ValueError names the file and what is wrong."""
    cfg = AlertsConfig(min_snr=args.min_snr, max_far_hz=args.max_far_hz,
                       wafer_bands=args.wafer_bands)
    records = run_alerts(args.events, args.out, cfg, args.voevent, args.tense)
    print(f"{len(records)} alert(s) written to {args.out}")
    for r in records:
        print(f"  {file_name(r)}  {r['alert_type']:<10} {r['alert_tense']:<9} "
              + (r.get("event_name", "") + "  " + r.get("update_message", "")).strip())
    return 0


if __name__ == "__main__":
    sys.exit(main(get_parser().parse_args()))
