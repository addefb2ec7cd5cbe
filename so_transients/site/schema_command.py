"""``so-transients schema``: the candidate table's columns (name, step, unit, meaning) as
Markdown. Built like a sotodlib site-pipeline element (:func:`get_parser`, :func:`main`)."""
from __future__ import annotations

import argparse
import sys


def get_parser(parser=None):
    if parser is None:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    return parser


def main(args) -> int:
    from so_transients.common.candidates import markdown

    print(markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main(get_parser().parse_args()))
