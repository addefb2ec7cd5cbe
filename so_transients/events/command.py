"""``so-transients events``: from a preprocess archive's detections to events, light curves,
light-curve fits and figures.

Built like a sotodlib site-pipeline element (:func:`get_parser`, :func:`main`; also run as
``python -m so_transients.events.command CONFIG``). The steps:

1. the archive's detections (``transient_fit``'s ``detected``) are joined into events and
   the events into sources (:func:`so_transients.events.tables.associate_detections`);
2. every group (wafer x band) of every observation whose time overlaps an event's
   light-curve window is a work unit: forced photometry of those events at every crossing
   (:mod:`so_transients.events.group_photometry`), dispatched through sotodlib's
   ``get_exec_env`` (a process pool here, MPI ranks on a cluster); finished units are kept,
   so a second run only does what is missing or changed;
3. the tables and one figure per event are written to the output folder::

       events.ecsv, events.fits              one row per event (with the nearest source of
                                             the config's `catalogue`, when it names one)
       lightcurves.ecsv, lightcurves.fits    one row per crossing and band (lightcurvedb's
                                             FluxMeasurement fields plus the TOD's own)
       lightcurve_fits.ecsv                  eq. 1 per event and band
       failures.ecsv                         units that failed: observation, group, error
       detections.ecsv                       the archive's detections, with their event_id
       cutouts.ecsv, cutouts/                per event and band, a sky cutout of its best
                                             crossing made from the TOD (FITS) and the
                                             detector time streams there (NPZ)
       figures/<name>.png                    light curve per band, position over the tracks
       units/                                the work units' results (resumable)

A unit that fails (an observation missing from the disk, a group that cannot be loaded) is
recorded with its reason; the other events are still measured and written.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np
from astropy.table import Table, vstack
from tqdm.auto import tqdm

from so_transients.common.parallel import executor, is_worker_rank, run_all
from so_transients.common.tables import for_writing
from so_transients.detect.error_scale import ErrorScale, median_scales
from so_transients.site.provenance import attach, provenance
from so_transients.site.results import (
    archive_entries, archive_status, archive_table, output_format
)
from so_transients.site.pipeline import archive_index
from so_transients.site.selection import ObsSelection, add_selection_arguments
from so_transients.events.config import EventsConfig, load_events_config
from so_transients.events.cutouts import write_cutouts
from so_transients.events.group_photometry import GroupJob, run_job, tracks_path
from so_transients.events.tables import (
    associate_detections, complete_events, crossmatch_events, fit_table, lightcurve_table
)
from so_transients.sources.catalog import read_catalogue, read_ephemerides

log = logging.getLogger(__name__)


def get_parser(parser=None):
    if parser is None:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", help="events YAML, or the preprocess (site) config itself")
    parser.add_argument("-o", "--out", help="output folder (default: the config's `output`, "
                                            "else <archive folder>/../events)")
    parser.add_argument("--nproc", type=int, help="worker processes (default: the config's)")
    parser.add_argument("--partial", action="store_true",
                        help="exit 0 when some groups failed (they are still listed)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    add_selection_arguments(parser)
    return parser


def obs_spans(preprocess) -> dict:
    """{obs_id: (start, stop)} ctimes from the ObsDb (start_time / stop_time; missing
    observations or fields: the whole time line)."""
    from sotodlib import core

    from so_transients.site.pipeline import read_config

    context = core.Context(read_config(preprocess)["context_file"])
    spans = {}
    for obs in context.obsdb.query():
        start, stop = obs.get("start_time"), obs.get("stop_time")
        spans[obs["obs_id"]] = (float(start) if start is not None else -np.inf,
                                float(stop) if stop is not None else np.inf)
    return spans


def file_stamp(path) -> str:
    """Size and modification time of a file ('' when missing)."""
    path = Path(path)
    if not path.is_file():
        return ""
    stat = path.stat()
    return f"{stat.st_size}:{stat.st_mtime_ns}"


def _error_scale(cands: Table, obs_id, tags) -> ErrorScale | None:
    """The error scales ``transient_fit`` measured in this group, in each scan direction
    (:func:`~so_transients.detect.error_scale.median_scales`; None: it fitted nothing in
    one of them)."""
    sel = np.asarray(cands["obs_id"]) == obs_id
    matched = [key for key in tags if key in cands.colnames]
    if tags and not matched:
        log.warning("%s: none of the group's keys %s is a candidate column: its error scale "
                    "is taken from the whole observation", obs_id, sorted(tags))
    for key in matched:
        sel &= np.asarray(cands[key]).astype(str) == str(tags[key])
    return median_scales(cands["error_scale"][sel], cands["direction"][sel])


def make_jobs(cfg: EventsConfig, events: Table, cands: Table, out: Path) -> list:
    """One :class:`GroupJob` per archived group that overlaps an event's window."""
    spans = obs_spans(cfg.preprocess)
    pc = cfg.photometry
    fit, find = cfg.fit, cfg.find
    lo, hi = events["t_first"] - pc.before_s, events["t_last"] + pc.after_s
    jobs = []
    for obs_id, tags, filename, dataset in archive_entries(archive_index(cfg.preprocess)):
        start, stop = spans.get(obs_id, (-np.inf, np.inf))
        mine = np.flatnonzero((hi >= start) & (lo <= stop))
        if not len(mine):
            continue
        job_events = [dict(event_id=int(events["event_id"][i]),
                           ra=float(np.radians(events["ra"][i])),
                           dec=float(np.radians(events["dec"][i])),
                           t_lo=float(lo[i]), t_hi=float(hi[i])) for i in mine]
        jobs.append(GroupJob(str(cfg.preprocess), obs_id, dict(tags), job_events,
                             _error_scale(cands, obs_id, tags), fit, find, pc,
                             str(out / "units" / f"{dataset}.ecsv"), file_stamp(filename)))
    return jobs


def write(table: Table, path: Path, prov: dict):
    """ECSV or FITS (by the suffix) with the provenance in the metadata; empty strings read
    back as '' (:func:`so_transients.common.tables.for_writing`)."""
    fmt = output_format(path, overwrite=True)
    out, extra = for_writing(attach(table.copy(), fmt, prov), fmt)
    out.write(path, format=fmt, overwrite=True, **extra)


def collect_units(statuses) -> Table:
    tables = [Table.read(s["path"]) for s in statuses if not s["error"]]
    tables = [t for t in tables if len(t)]
    if not tables:
        return Table()
    for t in tables:
        t.meta = {}
    return vstack(tables, metadata_conflicts="silent")


def failures_table(statuses, site_failed=None) -> Table:
    """The groups that failed: in the site pipeline (``site_failed``, an
    :class:`~so_transients.site.results.ArchiveStatus`'s ``failed``: their detections are
    missing) and in the forced photometry (``statuses``: their light-curve points are)."""
    failed = [{"obs_id": obs, "group": "/".join(group),
               "error": f"site pipeline: {kind}: {message}"}
              for (obs, group), (kind, message) in sorted((site_failed or {}).items())]
    failed += [s for s in statuses if s["error"]]
    return Table({"obs_id": [s["obs_id"] for s in failed] or np.zeros(0, str),
                  "group": [s["group"] for s in failed] or np.zeros(0, str),
                  "error": [s["error"] for s in failed] or np.zeros(0, str)})


def build_events(cfg: EventsConfig, progress=True, pool=None, as_completed=None,
                 selection: ObsSelection | None = None) -> dict:
    """Run every step, on the observations ``selection`` takes (all without); returns the
    tables written (events, lightcurves, fits, failures)."""
    out = Path(cfg.output)
    out.mkdir(parents=True, exist_ok=True)
    catalogue = read_catalogue(cfg.catalogue) if cfg.catalogue else None   # before the work
    status = archive_status(cfg.preprocess, selection)
    if not status.complete:
        log.warning("%s\n(the events use the groups in the archive)", status.report())
    chosen = None if selection is None or selection.everything else set(status.obs_ids)
    cands = archive_table(cfg.preprocess, detected_only=False, obs_ids=chosen)
    detections = cands[np.asarray(cands["detected"], bool)]
    events, labels = associate_detections(detections, cfg.association)
    jobs = make_jobs(cfg, events, cands, out) if len(events) else []
    statuses = run_all(run_job, jobs, "forced photometry", progress, pool, as_completed,
                       unit="group")
    failures = failures_table(statuses, status.failed)
    for s in statuses:
        if s["error"]:
            log.warning("%s %s: %s", s["obs_id"], s["group"], s.get("traceback", s["error"]))
    lightcurves = lightcurve_table(collect_units(statuses), events, detections, labels)
    fits = fit_table(lightcurves, cfg.lightcurve_fit)
    events = complete_events(events, lightcurves, cfg.spectral_min_snr)
    if catalogue is not None and len(events):
        ephemerides = read_ephemerides(cfg.catalogue, events["t_first"].min(),
                                       events["t_last"].max())
        events = crossmatch_events(events, catalogue, ephemerides, cfg.crossmatch)
    prov = provenance(cfg.preprocess, status.obs_ids)
    detections = detections.copy()
    detections["event_id"] = labels
    tables = dict(events=events, lightcurves=lightcurves, lightcurve_fits=fits,
                  failures=failures, detections=detections,
                  cutouts=write_cutouts(events, statuses, out))
    for name, table in tables.items():
        write(table, out / f"{name}.ecsv", prov)
        if name in ("events", "lightcurves"):
            write(table, out / f"{name}.fits", prov)
    write_figures(events, lightcurves, fits, detections, labels, statuses, out / "figures",
                  progress)
    return tables


def write_figures(events, lightcurves, fits, detections, labels, statuses, folder: Path,
                  progress=True):
    """One PNG per event (:func:`so_transients.events.figures.plot_event`)."""
    from so_transients.events.figures import plot_event

    tracks = {}
    for s in statuses:
        path = tracks_path(s["path"])
        if not s["error"] and path.is_file():
            with np.load(path) as held:
                for key in held.files:
                    tracks.setdefault(int(key.split("_")[0]), []).append(held[key])
    folder.mkdir(parents=True, exist_ok=True)
    for i in tqdm(range(len(events)), desc="event figures", disable=not progress):
        ev = events[i]
        eid = int(ev["event_id"])
        plot_event(ev, lightcurves[lightcurves["event_id"] == eid],
                   fits[fits["event_id"] == eid], detections[labels == eid],
                   tracks.get(eid, []), folder / f"event_{eid:04d}.png")


def summary(tables: dict, out: Path) -> str:
    ev, lc, failed = tables["events"], tables["lightcurves"], tables["failures"]
    lines = [f"{len(ev)} event(s) from {int(np.sum(ev['n_detections']))} detection(s); "
             f"{len(lc)} light-curve point(s) ({int(np.sum(ev['n_upper_limits']))} upper "
             f"limits); results in {out}"]
    for row in ev:
        lines.append(f"  {row['event_id']:4d} {row['name']}  {row['t_first_utc']}  "
                     f"bands {row['bands']:<10} wafers {row['wafers']:<12} "
                     f"peak {row['peak_flux']:.0f} +- {row['peak_flux_err']:.0f} mJy "
                     f"({row['peak_band']})  {row['n_crossings']} crossings"
                     + (f"  {row['cat_class']} {row['cat_source_name']}".rstrip()
                        if row["cat_class"] else "")
                     + (f"  [{row['note']}]" if row["note"] else ""))
    for row in failed:
        lines.append(f"  FAILED {row['obs_id']} {row['group']}: {row['error']}")
    return "\n".join(lines)


def run_events(cfg: EventsConfig, progress=True, selection=None):
    """:func:`build_events` with ``cfg.nproc`` workers from sotodlib's executor; None on an
    MPI worker rank (it served units until rank 0 finished)."""
    pool, as_completed = executor(cfg.nproc)
    if is_worker_rank(pool, cfg.nproc):
        return None
    try:
        return build_events(cfg, progress=progress, pool=pool, as_completed=as_completed,
                            selection=selection)
    finally:
        if pool is not None:
            pool.shutdown()


def main(args) -> int:
    """The command on :func:`get_parser`'s options."""
    return events_main(args.config, args.out, args.nproc, args.partial, args.quiet,
                       ObsSelection.from_args(args))


def events_main(config, out=None, nproc=None, partial=False, quiet=False, selection=None):
    """Exit status: 0 done, 1 when a work unit failed (0 with ``partial``)."""
    cfg = load_events_config(config, {"output": out, "nproc": nproc})
    tables = run_events(cfg, progress=not quiet, selection=selection)
    if tables is None:
        return 0
    print(summary(tables, Path(cfg.output)))
    if len(tables["failures"]):
        for row in tables["failures"]:
            print(f"so-transients events: FAILED {row['obs_id']} {row['group']}: {row['error']}",
                  file=sys.stderr)
        print(f"so-transients events: {len(tables['failures'])} group(s) failed; their "
              "detections or crossings are missing from the events and light curves"
              f"{' (--partial: exit 0)' if partial else ''}", file=sys.stderr)
        return 0 if partial else 1
    return 0


if __name__ == "__main__":
    sys.exit(main(get_parser().parse_args()))
