"""``so-transients summary DATASET``: what a dataset holds, as loaded through its
context.yaml. Built like a sotodlib site-pipeline element (:func:`get_parser`, :func:`main`)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def get_parser(parser=None):
    if parser is None:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="dataset folder (holds context.yaml), or the context.yaml")
    return parser


def main(args) -> int:
    from so_transients.site.pipeline import dataset_context
    from so_transients.site.summary import dataset_summary

    path = Path(args.dataset)
    print(dataset_summary(path if path.suffix in (".yaml", ".yml") else dataset_context(path)))
    return 0


if __name__ == "__main__":
    sys.exit(main(get_parser().parse_args()))
