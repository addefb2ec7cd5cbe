"""``so-transients catalog CONFIG -o FILE``: every group's detections from a preprocess
archive in one table (ECSV, FITS or CSV by suffix), with the groups expected, archived and
failed, and each group's losses; exit 1, naming them, when a group failed or is missing
(``--partial``: 0). Built like a sotodlib site-pipeline element (:func:`get_parser`,
:func:`main`); :func:`write_catalog` and :func:`report_failures` serve ``run`` too."""
from __future__ import annotations

import argparse
import sys

from so_transients.site.selection import ObsSelection, add_selection_arguments


def add_partial(parser):
    parser.add_argument("--partial", action="store_true",
                        help="exit 0 when some groups failed (each is still named)")


def add_max_lost(parser):
    parser.add_argument("--max-lost", type=float, default=0.3,
                        help="warn about groups that could not use more than this fraction of "
                             "their detectors (default 0.3)")


def get_parser(parser=None):
    if parser is None:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config",
                        help="site preprocess config (.yaml), or its archive index (.sqlite)")
    parser.add_argument("-o", "--out", default="detections.ecsv",
                        help="output table: .ecsv, .fits or .csv (default: detections.ecsv)")
    parser.add_argument("--all", action="store_true",
                        help="every candidate with its cut reason, not only detections")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    parser.add_argument("--groups", default=None, metavar="FILE",
                        help="also write each group's losses (detectors removed and why, "
                             "samples masked) to this table")
    add_selection_arguments(parser)
    add_partial(parser)
    add_max_lost(parser)
    return parser


def write_catalog(archive, out, overwrite, max_lost, candidates=False, by_time=False,
                  groups=None, selection=None):
    """Write the archive's detections (``candidates``: every candidate) to ``out``, print
    what was written, the groups expected, archived and failed, and each group's losses
    (also written to ``groups`` when given), of the observations ``selection`` takes;
    return the :class:`~so_transients.site.results.ArchiveStatus`."""
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


def report_failures(command, status, partial) -> int:
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


def main(args) -> int:
    from so_transients.site.results import output_format

    output_format(args.out, args.overwrite)          # refuse before the slow part
    status = write_catalog(args.config, args.out, args.overwrite, args.max_lost,
                           candidates=args.all, groups=args.groups, by_time=True,
                           selection=ObsSelection.from_args(args))
    return report_failures("catalog", status, args.partial)


if __name__ == "__main__":
    sys.exit(main(get_parser().parse_args()))
