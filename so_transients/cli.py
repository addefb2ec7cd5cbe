"""The ``so-transients`` command line.

Subcommands:

* ``simulate CONFIG``: simulate SO LAT observations into a sotodlib dataset;
* ``summary CONTEXT``: describe a dataset as loaded through its context.yaml;
* ``site-config DATASET``: the transient site preprocess config pointed at a dataset;
* ``catalog ARCHIVE_OR_CONFIG -o FILE``: every group's detections in one table (ECSV/FITS);
* ``schema``: the candidate table's columns (name, step, unit, meaning) as Markdown;
* ``campaign CONFIG``: an injection-recovery campaign (efficiency, thresholds, false positives);
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
    from .sim.config import load_config
    from .sim.simulate import simulate

    config = load_config(args.config, {"seed": args.seed, "output": args.out})
    t0 = time.time()
    result = simulate(config, overwrite=args.overwrite, progress=not args.quiet,
                      workers=getattr(args, "workers", 1))
    print(f"Simulated {len(result.obs_ids)} observation(s) in {time.time() - t0:.0f} s; "
          f"context: {result.context}")
    return result


def _summary(args):
    from .summary import dataset_summary

    print(dataset_summary(args.context))


def _site_config(args):
    from .site import write_site_config

    print(write_site_config(args.dataset, args.out))


def _catalog(args):
    from .results import archive_table, write_table

    table = archive_table(args.archive, detected_only=not args.all)
    path = write_table(table, args.out)
    print(f"{len(table)} {'candidates' if args.all else 'detections'} written to {path}")


def _schema(args):
    from .candidates import markdown

    print(markdown())


def _demo(args):
    from .demo import run_demo
    from .summary import dataset_summary

    args.config = args.config or DEMO_CONFIG
    args.seed = None
    args.overwrite = True
    result = _simulate(args)
    print(dataset_summary(result.context))
    print(run_demo(result.context.parent, nproc=args.nproc))


def _campaign(args):
    from .campaign.config import load_campaign
    from .campaign.run import executor, run_campaign

    cfg = load_campaign(args.config, {"output": args.out, "nproc": args.nproc})
    pool, as_completed = executor(cfg.nproc)
    if pool is None and cfg.nproc > 1:
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="so-transients", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="simulate SO LAT observations into a sotodlib dataset")
    p.add_argument("config", nargs="?", help="simulation YAML (default: built-in defaults)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("--seed", type=int, help="override the config's seed")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    p.add_argument("--workers", type=int, default=1,
                   help="threads generating detector chunks (same result for any number)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_simulate)

    p = sub.add_parser("summary", help="describe a dataset loaded through its context.yaml")
    p.add_argument("context", help="path to context.yaml")
    p.set_defaults(func=_summary)

    p = sub.add_parser("site-config", help="write the site preprocess config for a dataset")
    p.add_argument("dataset", help="dataset folder (holds context.yaml)")
    p.add_argument("-o", "--out", help="output YAML (default: DATASET/preprocess.yaml)")
    p.set_defaults(func=_site_config)

    p = sub.add_parser("catalog", help="collect detections from a preprocess archive")
    p.add_argument("archive", help="archive index (.sqlite) or preprocess config (.yaml)")
    p.add_argument("-o", "--out", default="detections.ecsv", help="ECSV or FITS output")
    p.add_argument("--all", action="store_true",
                   help="every candidate with its cut reason, not only detections")
    p.set_defaults(func=_catalog)

    p = sub.add_parser("schema", help="the candidate columns (name, step, unit, meaning)")
    p.set_defaults(func=_schema)

    p = sub.add_parser("campaign", help="injection-recovery campaign: efficiencies, detection "
                                        "thresholds, flux/pointing recovery, false positives")
    p.add_argument("config", help="campaign YAML (e.g. configs/campaign_quick.yaml)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("--nproc", type=int, help="worker processes (default: the config's)")
    p.add_argument("--restart", action="store_true",
                   help="discard units of a different config in the output folder")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_campaign)

    p = sub.add_parser("demo", help="simulate the default observation, run the site pipeline "
                                    "and compare detections with the injected flares")
    p.add_argument("--config", help=f"simulation YAML (default: {DEMO_CONFIG.name})")
    p.add_argument("-o", "--out", default="data/demo", help="output folder")
    p.add_argument("--nproc", type=int, default=2, help="site pipeline processes")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_demo)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        args.func(args)
    except (ValueError, FileNotFoundError, FileExistsError, RuntimeError) as exc:
        print(f"so-transients {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
