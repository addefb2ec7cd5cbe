"""``so-transients site-config DATASET``: the shipped site preprocess config pointed at a
dataset (``--mode`` production or paper, ``--max-far``, ``--known-sources``). Built like a
sotodlib site-pipeline element (:func:`get_parser`, :func:`main`)."""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

log = logging.getLogger(__name__)


def get_parser(parser=None):
    if parser is None:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="dataset folder (holds context.yaml)")
    parser.add_argument("-o", "--out", help="output YAML (default: DATASET/preprocess.yaml; "
                                            "paper mode DATASET/preprocess_paper.yaml, its "
                                            "archive in DATASET/preprocess_paper/)")
    parser.add_argument("--mode", choices=("production", "paper"), default="production",
                        help="production: coherent search with calibrated false-alarm rates "
                             "(configs/preprocess_production.yaml, default); paper: the "
                             "reference paper's method (configs/preprocess_paper.yaml)")
    parser.add_argument("--max-far", type=float, default=None, metavar="PER_HOUR",
                        help="false-alarm rate cut, per wafer-band-hour (production mode; "
                             "default the config's 0.005)")
    parser.add_argument("--known-sources", default=None, metavar="FILE",
                        help="ECSV/CSV of known sources (ra, dec) masked by transient_cuts")
    return parser


def main(args) -> int:
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
    return 0


if __name__ == "__main__":
    sys.exit(main(get_parser().parse_args()))
