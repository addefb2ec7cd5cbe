"""``so-transients run CONFIG``: sotodlib's site pipeline on a preprocess config, then the
catalogue of detections (in time order) and each group's losses; exit 1, naming them, when a
group failed (``--partial``: 0), 2 when the config or the archive is refused before anything
runs. Built like a sotodlib site-pipeline element (:func:`get_parser`, :func:`main`)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from so_transients.site.catalog_command import (
    add_max_lost, add_partial, report_failures, write_catalog
)
from so_transients.site.selection import ObsSelection, add_selection_arguments


def get_parser(parser=None):
    if parser is None:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config",
                        help="site preprocess config (e.g. from `so-transients site-config`)")
    parser.add_argument("-o", "--out", default=None,
                        help="detections table (default: detections.ecsv beside the archive)")
    parser.add_argument("--nproc", type=int, default=1,
                        help="worker processes of the site pipeline")
    parser.add_argument("--overwrite", action="store_true",
                        help="delete an archive whose groups other steps made, and make them "
                             "again (without it such an archive is refused, naming the groups)")
    add_selection_arguments(parser)
    add_partial(parser)
    add_max_lost(parser)
    return parser


def main(args) -> int:
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
    status = write_catalog(config, out, overwrite=True, max_lost=args.max_lost, by_time=True,
                           selection=selection)
    return report_failures("run", status, args.partial)


if __name__ == "__main__":
    sys.exit(main(get_parser().parse_args()))
