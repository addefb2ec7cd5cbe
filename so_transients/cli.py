"""The ``so-transients`` command line.

User commands:

* ``simulate [CONFIG]``: simulate SO LAT observations into a sotodlib dataset (``--list``: the
  tubes, wafers and bands it knows);
* ``summary DATASET``: describe a dataset as loaded through its context.yaml;
* ``site-config DATASET``: the site preprocess config pointed at a dataset (``--mode``
  production or paper, ``--max-far``, ``--known-sources``);
* ``run CONFIG``: sotodlib's site pipeline on it, then the catalogue (in time order) and each
  group's losses;
* ``catalog CONFIG -o FILE``: every group's detections in one table (ECSV, FITS or CSV by
  suffix), with which groups are missing from the archive and why;
* ``events CONFIG``: detections joined into events, forced-photometry light curves, fits
  and figures (:mod:`so_transients.events.command`);
* ``db ingest|query|lightcurve|migrate``: the events database across observations (SQLite
  by default, PostgreSQL by URL), idempotent ingest, association with what is stored;
* ``alerts EVENTS -o OUT``: one alert record per new or updated event (GCN unified-schema
  JSON, optionally VOEvent 2.0), validated against the package's JSON Schema;
* ``report EVENTS -o OUT``: a static site to vet the events: a sortable, filterable table,
  one page per event (light curve, sky cutout, time streams), labels a person exports;
* ``schema``: the candidate table's columns (name, step, unit, meaning) as Markdown;
* ``demo``: the main job on built-in default data (``make demo``).

``run``, ``catalog`` and ``events`` exit with status 1, naming each failed group, when any
group failed, unless ``--partial``; every command exits with status 2 on a refused input.

Validation studies (``so-transients study ...``): ``campaign CONFIG`` (injection-recovery:
efficiency, thresholds, false positives), ``combine RESULTS... -o OUT`` (several campaigns'
results as one), ``events-check CONFIG`` (the events step on simulated flares and noise),
``train-score CONFIG`` (the real-or-artefact score trained on simulated real wafers).
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys
from pathlib import Path

DEMO_CONFIG = Path(__file__).resolve().parent / "configs" / "sim_demo.yaml"

#: The commands: name -> (module with ``get_parser(parser)`` and ``main(args)``, help). As in
#: sotodlib's ``site_pipeline/cli.py``, a command's module is imported only when it runs (or
#: its ``--help`` is asked), so that ``so-transients --help`` answers at once.
COMMANDS = {
    "simulate": ("so_transients.sim.command",
                 "simulate SO LAT observations into a sotodlib dataset"),
    "summary": ("so_transients.site.summary_command",
                "describe a dataset loaded through its context.yaml"),
    "site-config": ("so_transients.site.config_command",
                    "write the site preprocess config for a dataset"),
    "run": ("so_transients.site.run_command",
            "run sotodlib's site pipeline on a preprocess config, then write the catalogue and "
            "each group's losses; exit 1 when a group failed"),
    "catalog": ("so_transients.site.catalog_command",
                "collect detections from a preprocess archive; exit 1 when a group failed or "
                "is missing"),
    "events": ("so_transients.events.command",
               "detections joined into events, with forced-photometry light curves, light-curve "
               "fits, spectral indices, sky cutouts and figures; exit 1 when a group failed"),
    "db": ("so_transients.database.command",
           "the events database across observations (SQLite or PostgreSQL): ingest an events "
           "folder, query events, a source's light curve"),
    "alerts": ("so_transients.alerts.command",
               "alert records of an events folder: GCN unified-schema JSON (and optionally "
               "VOEvent 2.0 XML), validated against the package's schema"),
    "report": ("so_transients.report.command",
               "a static site to vet an events folder's events: table, light curves, sky "
               "cutouts, time streams, labels"),
    "schema": ("so_transients.site.schema_command",
               "the candidate columns (name, step, unit, meaning)"),
    "demo": ("so_transients.demo",
             "simulate the default observation, run the production site config and compare "
             "detections with the injected flares"),
    "study": ("so_transients.campaign.command",
              "validation studies: campaigns, the events check, the score's training"),
}


def _common_options(default):
    """Options accepted before and after the subcommand (``default``: argparse.SUPPRESS in the
    subcommands, so that they do not reset a value given before the subcommand)."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-v", "--verbose", action="store_true", default=default,
                        help="log at INFO level")
    return common


def _command_named(argv) -> str:
    """The subcommand ``argv`` names: its first word that is not an option (the top-level
    options take no value); '' when none."""
    return next((a for a in argv if not a.startswith("-")), "")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser: every command of :data:`COMMANDS` with its help, and the
    options of ``command`` (all of them when None) from its module."""
    from so_transients import __version__

    parser = argparse.ArgumentParser(prog="so-transients", description=__doc__.splitlines()[0],
                                     parents=[_common_options(False)])
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    common = [_common_options(argparse.SUPPRESS)]
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, parents=common, help=help_text)
        p.set_defaults(module=module)
        if command is None or command == name:
            command_module = importlib.import_module(module)
            if name == "study":          # its sub-commands take the common options too
                command_module.get_parser(p, parents=common)
            else:
                command_module.get_parser(p)
    return parser


def configure_logging(verbose):
    """One handler on the root logger. sotodlib's logger has its own handler too: it stops
    propagating, else each of its lines would be printed twice."""
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("sotodlib").propagate = False


#: Optional dependencies by module, and the extra that installs them.
EXTRAS = {"sqlalchemy": "db", "psycopg": "db", "jsonschema": "alerts", "socat": "catalog",
          "toast": "toast"}


def _missing_extra(exc: ModuleNotFoundError, command) -> int:
    """Exit status 2 naming the extra a command needs (re-raised for any other module)."""
    extra = EXTRAS.get((exc.name or "").split(".")[0])
    if extra is None:
        raise exc
    print(f"so-transients {command}: error: {exc.name} is not installed: this command needs "
          f"the `{extra}` extra (pip install 'so_transients[{extra}]')", file=sys.stderr)
    return 2


def main(argv=None) -> int:
    """Exit status: 0 done, 1 done with failures (a group of ``run``, ``catalog`` or
    ``events`` failed, without ``--partial``), 2 refused (one line on stderr naming the file
    and what is wrong)."""
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    try:
        args = build_parser(_command_named(argv)).parse_args(argv)
    except ModuleNotFoundError as exc:
        return _missing_extra(exc, _command_named(argv))
    configure_logging(args.verbose)
    try:
        return importlib.import_module(args.module).main(args) or 0
    except ModuleNotFoundError as exc:
        return _missing_extra(exc, args.command)
    except (ValueError, OSError, RuntimeError) as exc:
        command = " ".join(filter(None, (args.command, getattr(args, "study", None))))
        print(f"so-transients {command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
