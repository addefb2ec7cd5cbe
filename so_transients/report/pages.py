"""The vetting site of an events folder: an index of every event and one page per event.

:func:`build_report` reads what ``so-transients events`` wrote (``events.ecsv``,
``detections.ecsv``, ``cutouts.ecsv`` and ``cutouts/``, ``figures/``) and, with an alerts
folder, the alert records of each event, and writes a self-contained static site::

    index.html              the events table: sorts, filters, labels, exports the labels
    events/event_<id>.html  the event: facts, light curve, sky cutout, time streams, detections
    img/                    the figures (the events command's, and the cutouts' and streams')
    cutouts/                the cutouts' FITS files
    alerts/                 copies of the event's alert records
    assets/                 the page's stylesheet and script (no network, no CDN)

Every link is relative: the folder opens from a laptop's disk as from a web server.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from datetime import datetime, timezone
from importlib.metadata import version as package_version
from pathlib import Path

import numpy as np
from astropy.table import Table
from jinja2 import Environment, FileSystemLoader, select_autoescape

from so_transients.common.parallel import executor, is_worker_rank, run_all
from so_transients.common.times import utc
from so_transients.report.plots import FigureJob, draw_event_figures
from so_transients.score.person_labels import DETECTION_COLUMNS

TEMPLATES = Path(__file__).parent / "templates"
ASSETS = ("report.css", "report.js")

#: Detection columns shown on an event page (those present), in this order.
SHOWN = ("obs_id", "wafer_slot", "bandpass", "scan", "t_peak", "snr_max", "snr_fit", "map_z",
         "far", "flux", "flux_err", "n_dets", "n_fit_dets", "chi2_red", "split_sigma",
         "moving", "real_score", "detected")


def _fmt(value, digits=1) -> str:
    """A number for a person: '-' when not measured."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if not np.isfinite(v):
        return "-"
    return f"{v:.{digits}f}" if abs(v) < 1e5 else f"{v:.3g}"


def _sortable(value) -> str:
    v = float(value)
    return repr(v) if np.isfinite(v) else ""


def far_text(event) -> str:
    """The false-alarm rate as shown: '<' before an upper limit, '-' when not measured."""
    far = float(event["far"])
    if not np.isfinite(far):
        return "-"
    return ("< " if bool(event["far_is_limit"]) else "") + f"{far:.3g}"


def flags_of(event, detections) -> str:
    """What a person should know before trusting the event: the events table's note,
    single-band detections, and its detections' consistency flags."""
    flags = []
    if str(event["note"]):
        flags.append(str(event["note"]))
    if bool(event["single_band"]):
        flags.append("single band")
    for name, what in (("moving", "moving"), ("pass_split", "halves disagree")):
        if name in detections.colnames:
            values = np.asarray(detections[name], bool)
            if (values if name == "moving" else ~values).any():
                flags.append(what)
    return "; ".join(flags)


def crossmatch_text(event) -> str:
    if not str(event["cat_class"]):
        return "no catalogue searched"
    if not str(event["catalogue"]):
        return "new: nothing catalogued within the match radius"
    ratio = float(event["cat_flux_ratio"])
    return (f"{event['cat_class']}: {event['cat_source_name']} ({event['catalogue']}, "
            f"id {event['cat_source_id']}), {_fmt(event['cat_separation'], 2)}' away"
            + (f", flux ratio {_fmt(ratio, 2)}" if np.isfinite(ratio) else ""))


def alerts_by_event(folder) -> dict:
    """{so_event_id: [(path, record)]} of the alert records (JSON) in ``folder``."""
    out = {}
    for path in sorted(Path(folder).glob("*.json")):
        record = json.loads(path.read_text())
        if "so_event_id" in record:
            out.setdefault(str(record["so_event_id"]), []).append((path, record))
    return out


def read_events_folder(folder) -> dict:
    """The tables a report needs, naming the folder when one is missing."""
    folder = Path(folder)
    tables = {}
    for name in ("events", "detections", "cutouts"):
        path = folder / f"{name}.ecsv"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing; is {folder} an events folder of "
                                    "`so-transients events` (version 0.9 or later)?")
        tables[name] = Table.read(path)
    return tables


def _event_context(event, dets, cutouts, figure, cutout_png, streams_png, alerts, page):
    snr = float(event["peak_flux"]) / float(event["peak_flux_err"])
    map_z = np.asarray(dets["map_z"], float) if "map_z" in dets.colnames else np.zeros(0)
    return dict(
        id=int(event["event_id"]), uuid=str(event["event_uuid"]),
        source_uuid=str(event["source_uuid"]), name=str(event["name"]),
        time=str(event["t_first_utc"]), time_last=str(event["t_last_utc"]),
        ctime=f"{float(event['t_first']):.2f}", ra=_fmt(event["ra"], 5), dec=_fmt(event["dec"], 5),
        pos_err=_fmt(event["pos_err"], 1), flux=_fmt(event["peak_flux"], 0),
        flux_err=_fmt(event["peak_flux_err"], 0), peak_band=str(event["peak_band"]),
        snr=_fmt(snr, 1), snr_sort=_sortable(snr), far=far_text(event),
        far_sort=_sortable(event["far"]), flux_sort=_sortable(event["peak_flux"]),
        map_z=_fmt(np.nanmax(map_z) if np.isfinite(map_z).any() else np.nan, 1),
        n_detections=int(event["n_detections"]), bands=str(event["bands"]),
        wafers=str(event["wafers"]), n_crossings=int(event["n_crossings"]),
        n_upper_limits=int(event["n_upper_limits"]), klass=str(event["cat_class"]),
        match=(str(event["cat_source_name"]) if str(event["catalogue"]) else ""),
        crossmatch=crossmatch_text(event), flags=flags_of(event, dets),
        figure=figure, cutout=cutout_png, streams=streams_png,
        fits=[str(p) for p in cutouts["file"]], alerts=alerts, page=page)


def _cell(name, value) -> str:
    """A detection's value as shown: times as UTC, rates in 3 significant figures."""
    if np.asarray(value).dtype.kind != "f":
        return str(value)
    if name == "t_peak":
        return str(utc(float(value))[0]) if np.isfinite(value) else "-"
    if name == "far":
        return f"{float(value):.3g}" if np.isfinite(value) else "-"
    return _fmt(value, 2)


def _detection_rows(dets):
    columns = [c for c in SHOWN if c in dets.colnames]
    return columns, [[_cell(c, r[c]) for c in columns] for r in dets]


def _features(dets) -> list:
    """The score's input columns of each detection (JSON-ready: NaN as None)."""
    return [{c: (float(r[c]) if c in dets.colnames and np.isfinite(float(r[c])) else None)
             for c in DETECTION_COLUMNS} for r in dets]


def build_report(events_folder, out, alerts_folder=None, title=None, progress=True,
                 nproc=2) -> Path | None:
    """Write the vetting site of ``events_folder`` into ``out``; returns its index.html (None
    on an MPI worker rank, which drew figures until rank 0 finished). The figures are drawn
    by ``nproc`` processes (sotodlib's executor)."""
    pool, as_completed = executor(nproc)
    if is_worker_rank(pool, nproc):
        return None
    try:
        return _build(Path(events_folder), Path(out), alerts_folder, title, progress, pool,
                      as_completed)
    finally:
        if pool is not None:
            pool.shutdown()


def _build(events_folder, out, alerts_folder, title, progress, pool, as_completed) -> Path:
    tables = read_events_folder(events_folder)
    events, detections, cutouts = tables["events"], tables["detections"], tables["cutouts"]
    alerts = alerts_by_event(alerts_folder) if alerts_folder else {}
    for sub in ("events", "img", "cutouts", "alerts", "assets"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    for name in ASSETS:
        shutil.copyfile(TEMPLATES / name, out / "assets" / name)
    env = Environment(loader=FileSystemLoader(TEMPLATES), autoescape=select_autoescape())
    det_ids = np.asarray(detections["event_id"], int)
    cut_ids = np.asarray(cutouts["event_id"], int)
    contexts, features, jobs = [], {}, []
    pages = [f"events/event_{int(e['event_id']):04d}.html" for e in events]
    for k, event in enumerate(events):
        eid = int(event["event_id"])
        dets, cuts = detections[det_ids == eid], cutouts[cut_ids == eid]
        figure = f"img/event_{eid:04d}.png"
        source_png = events_folder / "figures" / f"event_{eid:04d}.png"
        if source_png.is_file():
            shutil.copyfile(source_png, out / figure)
        cutout_png = streams_png = ""
        if len(cuts):
            for row in cuts:
                shutil.copyfile(events_folder / row["file"], out / row["file"])
            cutout_png, streams_png = f"img/event_{eid:04d}_cutout.png", \
                f"img/event_{eid:04d}_streams.png"
            jobs.append(FigureJob(dict(zip(event.colnames, event.as_void().tolist())), cuts,
                                  dets[[c for c in ("bandpass", "ra", "dec")
                                        if c in dets.colnames]],
                                  events_folder, out / cutout_png, out / streams_png))
        records = []
        for path, record in alerts.get(str(event["event_uuid"]), []):
            shutil.copyfile(path, out / "alerts" / path.name)
            for extra in (path.with_suffix(".xml"),):
                if extra.is_file():
                    shutil.copyfile(extra, out / "alerts" / extra.name)
            records.append(dict(path=f"alerts/{path.name}", name=path.name,
                                what=f"{record.get('alert_type', '')} "
                                     f"#{record.get('record_number', '')}"))
        ctx = _event_context(event, dets, cuts, figure, cutout_png, streams_png, records,
                             pages[k])
        columns, rows = _detection_rows(dets)
        (out / pages[k]).write_text(env.get_template("event.html.j2").render(
            e=ctx, det_columns=columns, det_rows=rows,
            prev=f"event_{int(events['event_id'][k - 1]):04d}.html" if k else "",
            next=(f"event_{int(events['event_id'][k + 1]):04d}.html"
                  if k + 1 < len(events) else "")))
        contexts.append(ctx)
        features[ctx["uuid"]] = _features(dets)
    run_all(draw_event_figures, jobs, "event figures", progress, pool, as_completed,
            unit="event")
    source = str(events_folder)
    meta = dict(report_id=hashlib.sha256(
        (source + "".join(c["uuid"] for c in contexts)).encode()).hexdigest()[:12],
        source=events_folder.name, detection_columns=list(DETECTION_COLUMNS))
    index = out / "index.html"
    index.write_text(env.get_template("index.html.j2").render(
        title=title or f"Events of {events_folder.resolve().parent.name}/{events_folder.name}",
        events=contexts, source=source, version=package_version("so_transients"),
        made=datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        classes=sorted({c["klass"] for c in contexts if c["klass"]}),
        detections_json=_script_json(features), meta_json=_script_json(meta)))
    return index


def _script_json(value) -> str:
    """JSON safe inside a <script> element (no '</' to close it early); jinja2's autoescape
    is off for it (Markup)."""
    from markupsafe import Markup

    return Markup(json.dumps(value).replace("</", "<\\/"))
