"""The ``so-transients`` command line.

Subcommands:

* ``simulate CONFIG``: simulate SO LAT observations into a sotodlib dataset;
* ``summary CONTEXT``: describe a dataset as loaded through its context.yaml;
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
    result = simulate(config, overwrite=args.overwrite, progress=not args.quiet)
    print(f"Simulated {len(result.obs_ids)} observation(s) in {time.time() - t0:.0f} s; "
          f"context: {result.context}")
    return result


def _summary(args):
    from .summary import dataset_summary

    print(dataset_summary(args.context))


def _demo(args):
    args.config = args.config or DEMO_CONFIG
    args.seed = None
    args.overwrite = True
    result = _simulate(args)
    from .summary import dataset_summary

    print(dataset_summary(result.context))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="so-transients", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="simulate SO LAT observations into a sotodlib dataset")
    p.add_argument("config", nargs="?", help="simulation YAML (default: built-in defaults)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("--seed", type=int, help="override the config's seed")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_simulate)

    p = sub.add_parser("summary", help="describe a dataset loaded through its context.yaml")
    p.add_argument("context", help="path to context.yaml")
    p.set_defaults(func=_summary)

    p = sub.add_parser("demo", help="simulate the default observation and summarize it")
    p.add_argument("--config", help=f"simulation YAML (default: {DEMO_CONFIG.name})")
    p.add_argument("-o", "--out", default="data/demo", help="output folder")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_demo)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        args.func(args)
    except (ValueError, FileNotFoundError, FileExistsError) as exc:
        print(f"so-transients {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
