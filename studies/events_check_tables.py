"""Several events checks side by side: the Markdown tables of the events results page.

    python studies/events_check_tables.py docs/results/data/events/events_check \\
        docs/results/data/events/events_check_short_sweeps docs/results/data/events/events_check_faint

Each argument is an events check's ``results`` folder (``<output>/results`` of
``so-transients study events-check CONFIG``); a run is named by its folder.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from so_transients.campaign.events_check import read_results, summary_markdown


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("folders", type=Path, nargs="+", help="results folders of events checks")
    args = p.parse_args(argv)
    print(summary_markdown({f.name: read_results(f) for f in args.folders}), end="")


if __name__ == "__main__":
    main()
