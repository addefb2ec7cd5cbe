"""``so-transients report EVENTS -o OUT``: the vetting site of an events folder.

Built like a sotodlib site-pipeline element (:func:`get_parser`, :func:`main`). Writes
``OUT/index.html`` and its pages (:mod:`so_transients.report.pages`): open it in a browser
from the disk, or serve the folder. ``--alerts`` links each event's alert records.
"""
from __future__ import annotations

import argparse
import sys
import time


def get_parser(parser=None):
    if parser is None:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("events", help="events folder (of `so-transients events`)")
    parser.add_argument("-o", "--out", required=True, help="folder of the site (index.html)")
    parser.add_argument("--alerts", help="alerts folder (of `so-transients alerts`): link "
                                         "each event's records")
    parser.add_argument("--title", help="the index page's title")
    parser.add_argument("--nproc", type=int, default=2,
                        help="processes drawing the figures (default 2; MPI ranks under mpirun)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    return parser


def main(args) -> int:
    from so_transients.report.pages import build_report

    t0 = time.time()
    index = build_report(args.events, args.out, args.alerts, args.title,
                         progress=not args.quiet, nproc=args.nproc)
    if index is None:      # an MPI worker rank: rank 0 wrote the site
        return 0
    print(f"Vetting pages written in {time.time() - t0:.1f} s: {index}")
    return 0


if __name__ == "__main__":
    sys.exit(main(get_parser().parse_args()))
