"""``so-transients db``: the events database across observations.

Subcommands (each takes ``--db``: a SQLite file path, default ``transients.db`` or the
environment's ``SO_TRANSIENTS_DB``, or a URL such as ``postgresql+psycopg://user@host/db``)::

    so-transients db ingest data/demo/events [more events folders] [--detections FILE]
    so-transients db query [--cone RA DEC RADIUS] [--start T] [--stop T] [--min-snr S]
                           [--sources] [-o FILE]
    so-transients db lightcurve SOURCE [-o FILE] [--lightcurvedb]
    so-transients db migrate

``ingest`` stores each observation of each run in one transaction (re-ingesting replaces) and
associates its events with the stored sources; ``query`` lists events (or sources) in a cone
(degrees), a time range (ctime or ISO UTC) and above a significance (``peak_snr``);
``lightcurve`` prints a source's light curve, or writes lightcurvedb's records of the source (its
Source, Instruments, FluxMeasurements and Cutouts, JSON); ``migrate`` brings an older database
to this version's schema.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import sqlalchemy as sa

from so_transients.common.redact import redacted
from so_transients.database.engine import database_url, migrate, open_database, open_engine
from so_transients.database.ingest import ingest_run
from so_transients.database.lightcurvedb import json_ready
from so_transients.database.queries import (
    counts, find_events, find_sources, lightcurvedb_records, lightcurve
)
from so_transients.database.runs import read_run
from so_transients.events.association import AssociationConfig
from so_transients.site.results import output_format

#: Default database (a SQLite file in the working folder) unless SO_TRANSIENTS_DB is set.
DEFAULT_DB = "transients.db"

#: Columns printed by ``query`` (every column goes to ``-o``).
EVENT_COLUMNS = ["event_uuid", "source_id", "source_name", "t_first_utc", "ra", "dec", "peak_flux",
                 "peak_flux_err", "peak_snr", "bands", "observation"]
SOURCE_COLUMNS = ["id", "uuid", "name", "ra", "dec", "pos_err", "n_events", "t_first", "t_last"]
POINT_COLUMNS = ["time", "bandpass", "flux", "flux_err", "snr", "upper_limit", "detected",
                 "obs_id", "wafer_slot", "scan", "run_event_id"]


def get_parser(parser=None):
    if parser is None:
        parser = argparse.ArgumentParser(prog="so-transients db",
                                         description=__doc__.splitlines()[0])
    db = argparse.ArgumentParser(add_help=False)
    db.add_argument("--db", default=os.environ.get("SO_TRANSIENTS_DB", DEFAULT_DB),
                    help="SQLite file or database URL (default: $SO_TRANSIENTS_DB, else "
                         f"{DEFAULT_DB})")
    sub = parser.add_subparsers(dest="db_command", required=True)

    p = sub.add_parser("ingest", parents=[db], help="store runs of so-transients events")
    p.add_argument("folders", nargs="+", help="output folders of so-transients events")
    p.add_argument("--detections", help="the runs' detections table (so-transients catalog; "
                                        "default: detections.ecsv in or next to the folder, "
                                        "else the archive); with one folder only")
    p.add_argument("--events-config", help="events YAML whose association settings the runs "
                                           "used (default: the defaults)")
    p.add_argument("--source-gap-hours", type=float,
                   help="events of one stored source at most this far apart in time "
                        "(default: the association's source_gap_hours)")

    p = sub.add_parser("query", parents=[db], help="events (or sources) by cone, time, S/N")
    p.add_argument("--cone", nargs=3, type=float, metavar=("RA", "DEC", "RADIUS"),
                   help="degrees")
    p.add_argument("--start", help="from this time (ctime or ISO UTC)")
    p.add_argument("--stop", help="to this time (ctime or ISO UTC)")
    p.add_argument("--min-snr", type=float, help="events with peak_snr at least this")
    p.add_argument("--event", help="the event of this UUID (an alert's so_event_id)")
    p.add_argument("--sources", action="store_true", help="list sources instead of events")
    p.add_argument("-o", "--out", help="write every column to this table (.ecsv, .fits, .csv)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")

    p = sub.add_parser("lightcurve", parents=[db], help="a source's light curve")
    p.add_argument("source", help="source id, its UUID, or an alert's so_source_id")
    p.add_argument("-o", "--out", help="write it to this table (.ecsv, .fits, .csv; .json "
                                       "with --lightcurvedb)")
    p.add_argument("--lightcurvedb", action="store_true",
                   help="as lightcurvedb's records (JSON): its Source, Instruments, "
                        "FluxMeasurements (Jy) and Cutouts")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")

    sub.add_parser("migrate", parents=[db], help="bring the schema to this version")
    return parser


def association(args) -> AssociationConfig:
    """The association settings of ``ingest``'s options."""
    if args.events_config:
        from so_transients.events.config import load_events_config

        cfg = load_events_config(args.events_config).association
    else:
        cfg = AssociationConfig()
    if args.source_gap_hours is not None:
        if not args.source_gap_hours > 0:
            raise ValueError(f"--source-gap-hours {args.source_gap_hours}: must be positive")
        cfg.source_gap_hours = args.source_gap_hours
    return cfg


def _ingest(args) -> int:
    if args.detections and len(args.folders) > 1:
        raise ValueError("--detections goes with one events folder only")
    cfg = association(args)
    runs = [read_run(folder, args.detections, cfg) for folder in args.folders]
    engine = open_database(args.db)
    for folder, run in zip(args.folders, runs):
        for r in ingest_run(engine, run, cfg):
            print(f"{folder}: {r.obs_id}: {r.events} event(s), {r.detections} detection(s), "
                  f"{r.lightcurve_points} light-curve point(s), {r.new_sources} new "
                  f"source(s){' (replaced)' if r.replaced else ''}")
    print(_counts_line(engine))
    return 0


def _counts_line(engine) -> str:
    return f"{engine.url!r}: " + ", ".join(f"{n} {t}" for t, n in counts(engine).items())


def _write(table, path, overwrite):
    fmt = output_format(path, overwrite)
    table.write(path, format=fmt, overwrite=overwrite)
    print(f"{len(table)} row(s) written to {path}")


def _show(table, names):
    """Print ``names`` of ``table``, floats to 7 significant digits."""
    shown = table[names].copy()
    for name in names:
        if shown[name].dtype.kind == "f":
            shown[name].info.format = ".7g"
    shown.pprint(max_lines=-1, max_width=-1)


def _query(args) -> int:
    engine = open_database(args.db, create=False)
    if args.sources:
        if args.min_snr is not None or args.event is not None:
            raise ValueError("--min-snr and --event select events: not with --sources")
        table = find_sources(engine, args.cone, args.start, args.stop)
        shown = SOURCE_COLUMNS
    else:
        table = find_events(engine, args.cone, args.start, args.stop, args.min_snr,
                            args.event)
        shown = EVENT_COLUMNS
    if args.out:
        _write(table, Path(args.out), args.overwrite)
    else:
        _show(table, shown)
    print(f"{len(table)} {'source' if args.sources else 'event'}(s)")
    return 0


def _lightcurve(args) -> int:
    engine = open_database(args.db, create=False)
    points = lightcurve(engine, args.source)
    src = points.meta["source"]
    if args.lightcurvedb:
        records = lightcurvedb_records(engine, args.source)
        text = json.dumps({kind: [json_ready(r) for r in rows] for kind, rows in records.items()},
                          indent=1)
        if args.out:
            path = Path(args.out)
            if path.exists() and not args.overwrite:
                raise FileExistsError(f"{path} exists: not overwritten (use --overwrite)")
            path.write_text(text + "\n")
            print(f"lightcurvedb records written to {path}: " + ", ".join(
                f"{len(rows)} {kind}" for kind, rows in records.items()))
        else:
            print(text)
        return 0
    if args.out:
        if Path(args.out).suffix.lower() != ".ecsv":    # the source is in the columns
            points.meta = {}
        _write(points, Path(args.out), args.overwrite)
    else:
        print(f"source {src['id']} {src['name']} ({src['uuid']}): ra {src['ra']:.5f} dec "
              f"{src['dec']:.5f} deg, {src['n_events']} event(s)")
        _show(points, POINT_COLUMNS)
    return 0


def _migrate(args) -> int:
    done = migrate(open_engine(args.db))
    print("\n".join(done) if done else f"{redacted(database_url(args.db))}: schema already "
          "current")
    return 0


COMMANDS = {"ingest": _ingest, "query": _query, "lightcurve": _lightcurve,
            "migrate": _migrate}


def main(args) -> int:
    """Run the subcommand of parsed ``args`` (:func:`get_parser`). Exit status 0; errors
    are raised as ValueError, OSError or RuntimeError naming the file or database."""
    try:
        return COMMANDS[args.db_command](args)
    except sa.exc.SQLAlchemyError as exc:
        url = sa.make_url(database_url(args.db))
        raise RuntimeError(f"{url!r}: {getattr(exc, 'orig', None) or exc}") from exc


if __name__ == "__main__":
    try:
        sys.exit(main(get_parser().parse_args()))
    except (ValueError, OSError, RuntimeError) as exc:
        print(f"so-transients db: error: {exc}", file=sys.stderr)
        sys.exit(2)
