"""The ``so-transients`` command line.

Subcommands:

* ``simulate CONFIG``: simulate SO LAT observations into a sotodlib dataset;
* ``summary CONTEXT``: describe a dataset as loaded through its context.yaml;
* ``site-config DATASET``: the transient site preprocess config pointed at a dataset;
* ``run CONFIG``: sotodlib's site pipeline on it, then the catalogue (in time order) and each
  group's losses; exit status 1, naming each failed group, unless ``--partial``;
* ``catalog ARCHIVE_OR_CONFIG -o FILE``: every group's detections in one table (ECSV, FITS or
  CSV by suffix), with which groups are missing from the archive and why;
* ``schema``: the candidate table's columns (name, step, unit, meaning) as Markdown;
* ``campaign CONFIG``: an injection-recovery campaign (efficiency, thresholds, false positives);
* ``campaign-combine RESULTS... -o OUT``: several campaigns' results (e.g. MF and UHF) as one;
* ``events CONFIG``: detections joined into events, forced-photometry light curves, fits
  and figures (:mod:`so_transients.events.command`);
* ``events-check CONFIG``: the events step measured on simulated flares and noise;
* ``demo``: the main job on built-in default data (``make demo``).
"""
from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

DEMO_CONFIG = Path(__file__).resolve().parent.parent / "configs" / "sim_demo.yaml"


def _simulate(args):
    _run_simulation(args)


def _run_simulation(args):
    """Simulate the dataset of ``args`` and return the simulation result."""
    from so_transients.sim.config import load_config
    from so_transients.sim.simulate import simulate

    config = load_config(args.config, {"seed": args.seed, "output": args.out})
    t0 = time.time()
    result = simulate(config, overwrite=args.overwrite, progress=not args.quiet,
                      workers=getattr(args, "workers", 1))
    print(f"Simulated {len(result.obs_ids)} observation(s) in {time.time() - t0:.0f} s; "
          f"context: {result.context}")
    return result


def _summary(args):
    from so_transients.site.summary import dataset_summary

    print(dataset_summary(args.context))


def _site_config(args):
    from so_transients.site.pipeline import write_site_config

    print(write_site_config(args.dataset, args.out))


def _write_catalog(archive, out, overwrite, max_lost, candidates=False, by_time=False,
                   groups=None):
    """Write the archive's detections (``candidates``: every candidate) to ``out``, print
    what was written, the groups expected, archived and failed, and each group's losses
    (also written to ``groups`` when given); return the :class:`ArchiveStatus`."""
    from so_transients.site.losses import group_losses, report
    from so_transients.site.results import archive_status, archive_table, write_table

    status = archive_status(archive)
    table = archive_table(archive, detected_only=not candidates)
    if by_time and len(table):
        table.sort("t_peak")
    path = write_table(table, out, config=status.config, obs_ids=status.obs_ids,
                       overwrite=overwrite)
    print(f"{len(table)} {'candidates' if candidates else 'detections'} written to {path}")
    print(status.report())
    losses = group_losses(archive, max_lost)
    print("Detectors per group:")
    print(report(losses))
    if groups:
        losses.write(groups, overwrite=overwrite)
    return status


def _catalog(args):
    """Exit status 1 with ``--strict`` when a group expected is not in the archive."""
    from so_transients.site.results import output_format

    output_format(args.out, args.overwrite)          # refuse before the slow part
    status = _write_catalog(args.archive, args.out, args.overwrite, args.max_lost,
                            candidates=args.all, groups=args.groups)
    if not status.complete:
        print(f"so-transients catalog: warning: {len(status.failed)} group(s) failed or missing; "
              "the table holds only the others", file=sys.stderr)
        return 1 if args.strict else 0
    return 0


def _run(args):
    """The site pipeline on a config, then its catalogue and each group's losses; exit status
    1 when any group failed (each named with its reason) unless ``--partial``."""
    from so_transients.site.pipeline import archive_index, run_site_pipeline

    config = Path(args.config)
    out = Path(args.out) if args.out else archive_index(config).parent / "detections.ecsv"
    done = run_site_pipeline(config, nproc=args.nproc, check=False)
    if done.returncode:
        print(f"so-transients run: {config}: the site pipeline stopped (exit "
              f"{done.returncode}):\n{done.stderr[-3000:]}", file=sys.stderr)
        return 1
    # a catalogue reads in time order
    status = _write_catalog(config, out, overwrite=True, max_lost=args.max_lost, by_time=True)
    if status.complete:
        return 0
    for (obs_id, group), (kind, message) in sorted(status.failed.items()):
        print(f"so-transients run: FAILED {obs_id} {'/'.join(group)}: {kind}: {message}",
              file=sys.stderr)
    print(f"so-transients run: {len(status.failed)} group(s) failed; the table holds the "
          f"others{' (--partial: exit 0)' if args.partial else ''}", file=sys.stderr)
    return 0 if args.partial else 1


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

    return main(args.config, args.out, args.nproc, args.strict, args.quiet)


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


def build_parser() -> argparse.ArgumentParser:
    from so_transients import __version__

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
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    p.add_argument("--workers", type=int, default=1,
                   help="threads generating detector chunks (same result for any number)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_simulate)

    p = add("summary", "describe a dataset loaded through its context.yaml")
    p.add_argument("context", help="path to context.yaml")
    p.set_defaults(func=_summary)

    p = add("site-config", "write the site preprocess config for a dataset")
    p.add_argument("dataset", help="dataset folder (holds context.yaml)")
    p.add_argument("-o", "--out", help="output YAML (default: DATASET/preprocess.yaml)")
    p.set_defaults(func=_site_config)

    p = add("run", "run sotodlib's site pipeline on a preprocess config, then write the "
                   "catalogue and each group's losses; exit 1 when a group failed")
    p.add_argument("config", help="site preprocess config (e.g. from `so-transients site-config`)")
    p.add_argument("-o", "--out", default=None,
                   help="detections table (default: detections.ecsv beside the archive)")
    p.add_argument("--nproc", type=int, default=1, help="worker processes of the site pipeline")
    p.add_argument("--partial", action="store_true",
                   help="exit 0 when some groups failed (their failures are still printed)")
    p.add_argument("--max-lost", type=float, default=0.3,
                   help="warn about groups that could not use more than this fraction of their "
                        "detectors (default 0.3)")
    p.set_defaults(func=_run)

    p = add("catalog", "collect detections from a preprocess archive")
    p.add_argument("archive", help="archive index (.sqlite) or preprocess config (.yaml)")
    p.add_argument("-o", "--out", default="detections.ecsv",
                   help="output table: .ecsv, .fits or .csv (default: detections.ecsv)")
    p.add_argument("--all", action="store_true",
                   help="every candidate with its cut reason, not only detections")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.add_argument("--strict", action="store_true",
                   help="exit with status 1 when a group is missing from the archive")
    p.add_argument("--groups", default=None, metavar="FILE",
                   help="also write each group's losses (detectors removed and why, samples "
                        "masked) to this table")
    p.add_argument("--max-lost", type=float, default=0.3,
                   help="warn about groups that could not use more than this fraction of their "
                        "detectors (default 0.3)")
    p.set_defaults(func=_catalog)

    p = add("schema", "the candidate columns (name, step, unit, meaning)")
    p.set_defaults(func=_schema)

    p = add("campaign", "injection-recovery campaign: efficiencies, detection "
                        "thresholds, flux/pointing recovery, false positives")
    p.add_argument("config", help="campaign YAML (e.g. studies/configs/campaign_quick.yaml)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("--nproc", type=int, help="worker processes (default: the config's)")
    p.add_argument("--restart", action="store_true",
                   help="discard units of a different config in the output folder")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_campaign)

    p = add("campaign-combine", "one set of result tables and figures from several "
                                "campaigns' results (e.g. an MF and a UHF campaign)")
    p.add_argument("results", nargs="+", help="campaign results folders (<output>/results)")
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.set_defaults(func=_campaign_combine)

    p = add("events", "detections joined into events, with forced-photometry light curves, "
                      "light-curve fits, spectral indices and figures")
    from so_transients.events.command import get_parser as events_parser
    events_parser(p)
    p.set_defaults(func=_events)

    p = add("events-check", "flares and noise through the site pipeline and the events "
                            "command, compared with the truth")
    p.add_argument("config", help="events-check YAML (e.g. studies/configs/events_check.yaml)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_events_check)

    p = add("demo", "simulate the default observation, run the site pipeline "
                    "and compare detections with the injected flares")
    p.add_argument("--config", help=f"simulation YAML (default: {DEMO_CONFIG.name})")
    p.add_argument("-o", "--out", default="data/demo", help="output folder")
    p.add_argument("--nproc", type=int, default=2, help="site pipeline processes")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_demo)
    return parser


def configure_logging(verbose):
    """One handler on the root logger. sotodlib's logger has its own handler too: it stops
    propagating, else each of its lines would be printed twice."""
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("sotodlib").propagate = False


def main(argv=None) -> int:
    """Exit status: 0 done, 1 done with failures (``catalog --strict``), 2 refused (one line
    on stderr naming the file and what is wrong)."""
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    try:
        return args.func(args) or 0
    except (ValueError, OSError, RuntimeError) as exc:
        print(f"so-transients {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
