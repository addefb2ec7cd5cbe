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
import logging
import sys
import time
from pathlib import Path

from so_transients.site.selection import ObsSelection, add_selection_arguments

log = logging.getLogger("so_transients.cli")
DEMO_CONFIG = Path(__file__).resolve().parent / "configs" / "sim_demo.yaml"


def _simulate(args):
    if args.list:
        return _simulate_list()
    _run_simulation(args)


def _simulate_list():
    from so_transients.sim.focal_plane import lat_layout

    print(f"{'tube':5} {'flavour':8} {'wafers':16} bands")
    for tube, flavour, wafers, bands in lat_layout():
        print(f"{tube:5} {flavour:8} {' '.join(wafers):16} {' '.join(bands)}")


def _run_simulation(args):
    """Simulate the dataset of ``args`` and return the simulation result."""
    from so_transients.database.queries import parse_time
    from so_transients.sim.config import load_config
    from so_transients.sim.simulate import simulate

    start = getattr(args, "start", None)
    config = load_config(args.config, {
        "seed": args.seed, "output": args.out,
        "observation": {"duration": getattr(args, "duration", None),
                        "start": None if start is None else parse_time(start)},
        "instrument": {"tubes": getattr(args, "tubes", None),
                       "wafers": getattr(args, "wafers", None),
                       "bands": getattr(args, "bands", None)}})
    t0 = time.time()
    result = simulate(config, overwrite=args.overwrite, progress=not args.quiet,
                      workers=getattr(args, "workers", 1))
    print(f"Simulated {len(result.obs_ids)} observation(s) in {time.time() - t0:.0f} s; "
          f"context: {result.context}")
    return result


def _summary(args):
    from so_transients.site.pipeline import dataset_context
    from so_transients.site.summary import dataset_summary

    path = Path(args.dataset)
    print(dataset_summary(path if path.suffix in (".yaml", ".yml") else dataset_context(path)))


def _site_config(args):
    from so_transients.site.pipeline import PAPER, PRODUCTION, dataset_context, write_site_config

    if args.max_far is not None and args.mode == "paper":
        raise ValueError("--max-far needs the production mode (the paper's method has no "
                         "transient_significance step)")
    overrides = {}
    if args.max_far is not None:
        from so_transients.significance.far import SignificanceConfig
        SignificanceConfig(max_far=args.max_far)        # refused now, not in every group
        overrides["transient_significance"] = {"calc": {"max_far": args.max_far}}
    if args.known_sources is not None:
        from so_transients.sources.catalog import read_catalogue
        known = read_catalogue(args.known_sources, owner="--known-sources")
        if not len(known):
            log.warning("--known-sources %s lists no source: nothing will be masked",
                        args.known_sources)
        overrides["transient_cuts"] = {"calc": {"known_sources":
                                                str(Path(args.known_sources).resolve())}}
    template = PRODUCTION if args.mode == "production" else PAPER
    results, out = None, args.out
    if args.mode == "paper":     # its own archive: never the production config's results
        folder = dataset_context(args.dataset).parent
        results = folder / "preprocess_paper"
        out = out or folder / "preprocess_paper.yaml"
    print(write_site_config(args.dataset, out, template=template, overrides=overrides,
                            results=results))


def _write_catalog(archive, out, overwrite, max_lost, candidates=False, by_time=False,
                   groups=None, selection=None):
    """Write the archive's detections (``candidates``: every candidate) to ``out``, print
    what was written, the groups expected, archived and failed, and each group's losses
    (also written to ``groups`` when given), of the observations ``selection`` takes;
    return the :class:`ArchiveStatus`."""
    from so_transients.site.losses import group_losses, report
    from so_transients.site.results import archive_status, archive_table, write_table

    status = archive_status(archive, selection)
    chosen = None if selection is None or selection.everything else set(status.obs_ids)
    table = archive_table(archive, detected_only=not candidates, obs_ids=chosen)
    if by_time and len(table):
        table.sort("t_peak")
    path = write_table(table, out, config=status.config, obs_ids=status.obs_ids,
                       overwrite=overwrite)
    print(f"{len(table)} {'candidates' if candidates else 'detections'} written to {path}")
    print(status.report())
    losses = group_losses(archive, max_lost, obs_ids=chosen)
    print("Detectors per group:")
    print(report(losses))
    if groups:
        losses.write(groups, overwrite=overwrite)
    return status


def _failures(command, status, partial) -> int:
    """Name each failed or missing group of ``status`` on stderr; the exit status (1 when
    any, 0 with ``partial``)."""
    if status.complete:
        return 0
    for (obs_id, group), (kind, message) in sorted(status.failed.items()):
        print(f"so-transients {command}: FAILED {obs_id} {'/'.join(group)}: {kind}: {message}",
              file=sys.stderr)
    print(f"so-transients {command}: warning: {len(status.failed)} group(s) failed or "
          f"missing; the table holds only the others"
          f"{' (--partial: exit 0)' if partial else ''}", file=sys.stderr)
    return 0 if partial else 1


def _catalog(args):
    from so_transients.site.results import output_format

    output_format(args.out, args.overwrite)          # refuse before the slow part
    status = _write_catalog(args.config, args.out, args.overwrite, args.max_lost,
                            candidates=args.all, groups=args.groups, by_time=True,
                            selection=ObsSelection.from_args(args))
    return _failures("catalog", status, args.partial)


def _run(args):
    """The site pipeline on a config, then its catalogue and each group's losses."""
    from so_transients.site.pipeline import archive_index, build_steps, run_site_pipeline
    from so_transients.site.results import remove_orphans
    from so_transients.site.steps_record import clear_archive, record_groups, stale_groups
    from so_transients.site.turnarounds import short_observations

    config = Path(args.config)
    selection = ObsSelection.from_args(args)
    out = Path(args.out) if args.out else archive_index(config).parent / "detections.ecsv"
    short = short_observations(config, selection)
    if short:                # refused before the site pipeline stops inside sotodlib
        raise ValueError("\n  ".join(["observations too short for this config:", *short]))
    build_steps(config)      # a misspelt key or a value out of range: refused, nothing run
    stale = stale_groups(config)
    if stale and not args.overwrite:
        shown = ", ".join(stale[:4]) + (f" and {len(stale) - 4} more" if len(stale) > 4 else "")
        raise ValueError(f"{config}: the archive {archive_index(config)} holds {len(stale)} "
                         f"group(s) made with other steps than this config's (or by a run "
                         f"that recorded none): {shown}; rerun with --overwrite to make them "
                         f"again, or point archive: at another folder")
    if stale:
        for path in clear_archive(config):
            print(f"so-transients run: --overwrite: deleted {path}", file=sys.stderr)
    for item in remove_orphans(config):       # left by a run that was stopped
        print(f"so-transients run: removed {item} (written, never indexed)", file=sys.stderr)
    try:
        done = run_site_pipeline(config, nproc=args.nproc, check=False,
                                 extra_args=selection.preprocess_args())
    finally:                                   # stopped or not: the groups it made are its
        if archive_index(config).is_file():
            record_groups(config)
    if done.returncode:
        print(f"so-transients run: {config}: the site pipeline stopped (exit "
              f"{done.returncode}):\n{done.stderr[-3000:]}", file=sys.stderr)
        return 1
    # the transient steps' warnings (e.g. a known-source list without sources), once each
    for line in dict.fromkeys(done.stderr.splitlines()):
        if "WARNING" in line and "so_transients" in line:
            print(line, file=sys.stderr)
    status = _write_catalog(config, out, overwrite=True, max_lost=args.max_lost, by_time=True,
                            selection=selection)
    return _failures("run", status, args.partial)


def _schema(args):
    from so_transients.common.candidates import markdown

    print(markdown())


def _demo(args):
    from so_transients.demo import run_demo
    from so_transients.site.summary import dataset_summary

    args.config = args.config or DEMO_CONFIG
    args.seed = None
    args.overwrite = True
    result = _run_simulation(args)
    print(dataset_summary(result.context))
    print(run_demo(result.context.parent, nproc=args.nproc))


def _campaign(args):
    from so_transients.campaign.config import load_campaign
    from so_transients.campaign.run import run_campaign
    from so_transients.common.parallel import executor, is_worker_rank

    cfg = load_campaign(args.config, {"output": args.out, "nproc": args.nproc})
    pool, as_completed = executor(cfg.nproc)
    if is_worker_rank(pool, cfg.nproc):
        return          # an MPI worker rank: it served units until rank 0 finished
    t0 = time.time()
    try:
        folder = run_campaign(cfg, restart=args.restart, progress=not args.quiet, pool=pool,
                              as_completed=as_completed)
    finally:
        if pool is not None:
            pool.shutdown()
    print((folder / "thresholds.md").read_text())
    print(f"Campaign done in {time.time() - t0:.0f} s; results in {folder}")


def _events(args):
    from so_transients.events.command import main

    return main(args.config, args.out, args.nproc, args.partial, args.quiet,
                ObsSelection.from_args(args))


def _db(args):
    from so_transients.database.command import main

    return main(args)


def _alerts(args):
    from so_transients.alerts.command import main

    return main(args)


def _report(args):
    from so_transients.report.command import main

    return main(args)


def _events_check(args):
    from astropy.table import Table

    from so_transients.campaign.events_check import EventsCheckConfig, run_events_check

    cfg = EventsCheckConfig.read(args.config, args.out)
    t0 = time.time()
    folder = run_events_check(cfg, progress=not args.quiet)
    for name in ("events_per_flare", "lightcurve_recovery", "false_events"):
        print(f"\n{name}:")
        Table.read(folder / f"{name}.ecsv").pprint(max_lines=-1, max_width=-1)
    print(f"Events check done in {time.time() - t0:.0f} s; results in {folder}")


def _train_score(args):
    from so_transients.campaign.score_training import (
        ScoreTrainingConfig, markdown, run_score_training
    )

    cfg = ScoreTrainingConfig.read(args.config, args.out, args.labels)
    t0 = time.time()
    path, figures = run_score_training(cfg, progress=not args.quiet, model_out=args.model)
    print(markdown(figures))
    print(f"Score model trained in {time.time() - t0:.0f} s: {path}")


def _campaign_combine(args):
    from so_transients.campaign.combine import combine_results

    folder = combine_results(args.results, args.out)
    print((folder / "summary.md").read_text())
    print(f"Combined results in {folder}")


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
    """The command line's parser; ``command``: build only that subcommand's own options among
    those whose module is slow to import (``events``, ``db``, ``alerts``: the others are
    listed with their help), so that ``--help`` and the other commands start at once."""
    from so_transients import __version__

    def full(name):
        return command is None or command == name

    parser = argparse.ArgumentParser(prog="so-transients", description=__doc__.splitlines()[0],
                                     parents=[_common_options(False)])
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    common = [_common_options(argparse.SUPPRESS)]

    def add(name, help_text):
        return sub.add_parser(name, parents=common, help=help_text)

    p = add("simulate", "simulate SO LAT observations into a sotodlib dataset")
    p.add_argument("config", nargs="?", help="simulation YAML (default: built-in defaults)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("--seed", type=int, help="override the config's seed")
    p.add_argument("--duration", type=float, help="seconds per observation")
    p.add_argument("--start", help="first observation's start, ctime or ISO UTC (it names the "
                                   "obs_id; default: the config's)")
    p.add_argument("--tubes", nargs="+", metavar="TUBE", help="LAT tube slots (see --list)")
    p.add_argument("--wafers", nargs="+", metavar="WAFER",
                   help="wafer slots of those tubes (default: the config's)")
    p.add_argument("--bands", nargs="+", metavar="BAND",
                   help="bands (default: both bands of each tube)")
    p.add_argument("--list", action="store_true",
                   help="list the tubes, wafers and bands that can be simulated, and stop")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    p.add_argument("--workers", type=int, default=1,
                   help="threads generating detector chunks (same result for any number)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_simulate)

    p = add("summary", "describe a dataset loaded through its context.yaml")
    p.add_argument("dataset", help="dataset folder (holds context.yaml), or the context.yaml")
    p.set_defaults(func=_summary)

    p = add("site-config", "write the site preprocess config for a dataset")
    p.add_argument("dataset", help="dataset folder (holds context.yaml)")
    p.add_argument("-o", "--out", help="output YAML (default: DATASET/preprocess.yaml; "
                                       "paper mode DATASET/preprocess_paper.yaml, its archive "
                                       "in DATASET/preprocess_paper/)")
    p.add_argument("--mode", choices=("production", "paper"), default="production",
                   help="production: coherent search with calibrated false-alarm rates "
                        "(configs/preprocess_production.yaml, default); paper: the reference "
                        "paper's method (configs/preprocess_paper.yaml)")
    p.add_argument("--max-far", type=float, default=None, metavar="PER_HOUR",
                   help="false-alarm rate cut, per wafer-band-hour (production mode; default "
                        "the config's 0.005)")
    p.add_argument("--known-sources", default=None, metavar="FILE",
                   help="ECSV/CSV of known sources (ra, dec) masked by transient_cuts")
    p.set_defaults(func=_site_config)

    def partial(p):
        p.add_argument("--partial", action="store_true",
                       help="exit 0 when some groups failed (each is still named)")

    def max_lost(p):
        p.add_argument("--max-lost", type=float, default=0.3,
                       help="warn about groups that could not use more than this fraction of "
                            "their detectors (default 0.3)")

    p = add("run", "run sotodlib's site pipeline on a preprocess config, then write the "
                   "catalogue and each group's losses; exit 1 when a group failed")
    p.add_argument("config", help="site preprocess config (e.g. from `so-transients site-config`)")
    p.add_argument("-o", "--out", default=None,
                   help="detections table (default: detections.ecsv beside the archive)")
    p.add_argument("--nproc", type=int, default=1, help="worker processes of the site pipeline")
    p.add_argument("--overwrite", action="store_true",
                   help="delete an archive whose groups other steps made, and make them again "
                        "(without it such an archive is refused, naming the groups)")
    add_selection_arguments(p)
    partial(p)
    max_lost(p)
    p.set_defaults(func=_run)

    p = add("catalog", "collect detections from a preprocess archive; exit 1 when a group "
                       "failed or is missing")
    p.add_argument("config", help="site preprocess config (.yaml), or its archive index (.sqlite)")
    p.add_argument("-o", "--out", default="detections.ecsv",
                   help="output table: .ecsv, .fits or .csv (default: detections.ecsv)")
    p.add_argument("--all", action="store_true",
                   help="every candidate with its cut reason, not only detections")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.add_argument("--groups", default=None, metavar="FILE",
                   help="also write each group's losses (detectors removed and why, samples "
                        "masked) to this table")
    add_selection_arguments(p)
    partial(p)
    max_lost(p)
    p.set_defaults(func=_catalog)

    p = add("events", "detections joined into events, with forced-photometry light curves, "
                      "light-curve fits, spectral indices and figures; exit 1 when a group "
                      "failed")
    if full("events"):
        from so_transients.events.command import get_parser as events_parser
        events_parser(p)
    p.set_defaults(func=_events)

    p = add("db", "the events database across observations (SQLite or PostgreSQL): ingest "
                  "an events folder, query events, a source's light curve")
    if full("db"):
        from so_transients.database.command import get_parser as db_parser
        db_parser(p)
    p.set_defaults(func=_db)

    p = add("alerts", "alert records of an events folder: GCN unified-schema JSON (and "
                      "optionally VOEvent 2.0 XML), validated against the package's schema")
    if full("alerts"):
        from so_transients.alerts.command import get_parser as alerts_parser
        alerts_parser(p)
    p.set_defaults(func=_alerts)

    p = add("report", "a static site to vet an events folder's events: table, light curves, "
                      "sky cutouts, time streams, labels")
    from so_transients.report.command import get_parser as report_parser   # imports little
    report_parser(p)
    p.set_defaults(func=_report)

    p = add("schema", "the candidate columns (name, step, unit, meaning)")
    p.set_defaults(func=_schema)

    p = add("demo", "simulate the default observation, run the production site config "
                    "and compare detections with the injected flares")
    p.add_argument("--config", help=f"simulation YAML (default: {DEMO_CONFIG.name})")
    p.add_argument("-o", "--out", default="data/demo", help="output folder")
    p.add_argument("--nproc", type=int, default=2, help="site pipeline processes")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_demo)

    study = add("study", "validation studies: campaigns and the events check").add_subparsers(
        dest="study", required=True,
        metavar="{campaign,combine,events-check,train-score}")

    def add_study(name, help_text):
        return study.add_parser(name, parents=common, help=help_text)

    p = add_study("campaign", "injection-recovery campaign: efficiency, detection "
                              "thresholds, flux/pointing recovery, false positives")
    p.add_argument("config", help="campaign YAML (e.g. studies/configs/campaign_quick.yaml)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("--nproc", type=int, help="worker processes (default: the config's)")
    p.add_argument("--restart", action="store_true",
                   help="discard units of a different config in the output folder")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_campaign)

    p = add_study("combine", "one set of result tables and figures from several campaigns' "
                             "results (e.g. an MF and a UHF campaign)")
    p.add_argument("results", nargs="+", help="campaign results folders (<output>/results)")
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.set_defaults(func=_campaign_combine)

    p = add_study("events-check", "flares and noise through the site pipeline and the events "
                                  "command, compared with the truth")
    p.add_argument("config", help="events-check YAML (e.g. studies/configs/events_check.yaml)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_events_check)

    p = add_study("train-score", "the real-or-artefact score: labelled candidates of simulated "
                                 "real wafers, the model trained and measured on held-out "
                                 "seeds and another scan pattern")
    p.add_argument("config", help="training YAML (e.g. studies/configs/score_training.yaml)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("--model", help="model file to write (default: OUT/real_score.json)")
    p.add_argument("--labels", nargs="+", default=[], metavar="CSV",
                   help="labels a person exported from `so-transients report` pages, trained "
                        "on beside the simulated ones")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_train_score)
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
        return args.func(args) or 0
    except ModuleNotFoundError as exc:
        return _missing_extra(exc, args.command)
    except (ValueError, OSError, RuntimeError) as exc:
        command = " ".join(filter(None, (args.command, getattr(args, "study", None))))
        print(f"so-transients {command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
