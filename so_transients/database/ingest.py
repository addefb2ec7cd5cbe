"""Ingesting runs: each observation in one transaction, its events associated with the
sources already stored.

For each observation of a run (:func:`so_transients.database.runs.split`), in one write
transaction (:func:`so_transients.database.engine.write_transaction`, which serialises
writers):

1. its observation row is created or updated, and the rows an earlier ingest stored with it
   are deleted (re-ingesting replaces, never duplicates);
2. its events are associated with the stored sources near them by the events' own rules
   (:func:`so_transients.events.association.link` with ``source_gap_hours`` as the time gap,
   each source spanning its events' times): an event linked to a stored source keeps that
   source's id (the oldest, when it links to several), events linked to no stored source make
   new sources;
3. its events, detections, light-curve points and fits are inserted with their source ids
   (an event stored before, by its ``event_uuid``, keeps its row id);
4. the sources it touched get their position (inverse-variance weighted mean of their events,
   :func:`so_transients.events.association.weighted_position`), time span and count again; a
   source left without events is deleted.

A failure or a killed process inside the transaction leaves the observation as it was before.
"""
from __future__ import annotations

import logging
import math
import uuid
from dataclasses import dataclass
from pathlib import Path
from datetime import datetime, timezone

import numpy as np
import sqlalchemy as sa
from astropy.table import Table

from so_transients.common.angles import ARCSEC, DEG
from so_transients.database import schema
from so_transients.database.engine import check_schema, write_transaction
from so_transients.database.runs import ObservationRows, Run, split
from so_transients.events.association import AssociationConfig, link, weighted_position
from so_transients.events.tables import event_name

log = logging.getLogger(__name__)


@dataclass
class IngestResult:
    """What one observation's ingest did."""
    obs_id: str
    events: int
    detections: int
    lightcurve_points: int
    new_sources: int
    replaced: bool


def _python(value):
    """A numpy scalar as a Python value; NaN as None."""
    value = value.item() if hasattr(value, "item") else value
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def table_rows(table: Table, sql_table: sa.Table, fixed: dict, per_row: dict | None = None):
    """Insert dicts for ``sql_table`` from astropy ``table``: declared columns under their
    database names, ``fixed`` values for every row, ``per_row`` {column: values}, and the
    table's other columns in ``extra``."""
    declared = schema.DECLARED[sql_table.name]
    by_file = {c.name: db for db, c in declared.items()}
    columns = {name: table[name].tolist() for name in table.colnames}
    stored = [name for name in table.colnames if name in by_file]
    others = [name for name in table.colnames if name not in by_file]
    rows = []
    for i in range(len(table)):
        row = dict(fixed)
        row.update({by_file[name]: _python(columns[name][i]) for name in stored})
        row.update({key: _python(values[i]) for key, values in (per_row or {}).items()})
        row["extra"] = {name: _python(columns[name][i]) for name in others} or None
        rows.append(row)
    return rows


def _ra_window(col, ra, half_width):
    """SQL condition: RA column ``col`` (deg) within ``half_width`` (deg, along RA) of
    ``ra``, across 0/360; None when the window covers every RA."""
    if half_width >= 180.0:
        return None
    lo, hi = (ra - half_width) % 360.0, (ra + half_width) % 360.0
    return sa.and_(col >= lo, col <= hi) if lo <= hi else sa.or_(col >= lo, col <= hi)


def box_condition(table: sa.Table, ra, dec, radius):
    """SQL condition: ``table``'s ra/dec (deg) within a box holding the circle of ``radius``
    degrees about (``ra``, ``dec``)."""
    cond = table.c.dec.between(dec - radius, dec + radius)
    cos_dec = math.cos(math.radians(min(abs(dec) + radius, 90.0)))
    half = radius / cos_dec if cos_dec > 1e-9 else 360.0
    window = _ra_window(table.c.ra, ra, min(half, 360.0))
    return cond if window is None else sa.and_(cond, window)


def nearby_sources(conn, events: Table, cfg: AssociationConfig) -> list:
    """The stored sources (rows) that could link to ``events``: within the largest
    association separation and ``source_gap_hours`` of one of them."""
    radius = cfg.max_separation / DEG
    gap = cfg.source_gap_hours * 3600.0
    conds = [sa.and_(box_condition(schema.SOURCES, float(ev["ra"]), float(ev["dec"]), radius),
                     schema.SOURCES.c.t_last >= float(ev["t_first"]) - gap,
                     schema.SOURCES.c.t_first <= float(ev["t_last"]) + gap) for ev in events]
    if not conds:
        return []
    query = sa.select(schema.SOURCES).where(sa.or_(*conds)).order_by(schema.SOURCES.c.id)
    return list(conn.execute(query).mappings())


def _run_source_uuid(events: Table, i) -> str:
    return str(events["source_uuid"][i]) if "source_uuid" in events.colnames else ""


def associate(conn, events: Table, cfg: AssociationConfig) -> tuple:
    """``(source ids, new ids)``: the source of each event (see the module), creating the new
    sources (their position and span are set by :func:`refresh_sources`). An event whose
    run ``source_uuid`` the database already knows (as a source's UUID, or an earlier event's
    ``source_uuid``) joins that source too; a new source takes its first event's
    ``source_uuid`` (free: none of its events' UUIDs is known, or it would have joined), so
    that alerts' ``so_source_id`` is the database's source UUID."""
    if not len(events):
        return np.zeros(0, int), []
    stored = nearby_sources(conn, events, cfg)
    sigma = lambda pos_err: np.asarray([np.nan if v is None else v for v in pos_err],
                                       float) * ARCSEC
    ra = np.r_[[s["ra"] for s in stored], np.asarray(events["ra"], float)] * DEG
    dec = np.r_[[s["dec"] for s in stored], np.asarray(events["dec"], float)] * DEG
    err = np.r_[sigma([s["pos_err"] for s in stored]), sigma(events["pos_err"])]
    spans = np.r_[np.reshape([(s["t_first"], s["t_last"]) for s in stored], (-1, 2)),
                  np.c_[events["t_first"], events["t_last"]]]
    labels = link(ra, dec, err, spans, cfg, max_gap=cfg.source_gap_hours * 3600.0)
    n = len(stored)
    ids, new = np.zeros(len(events), int), []
    for group in np.unique(labels[n:]):
        members = np.flatnonzero(labels == group)
        mine = members[members >= n] - n
        old = [stored[i]["id"] for i in members if i < n]
        old += [k for k in (source_of_uuid(conn, _run_source_uuid(events, i)) for i in mine)
                if k is not None]
        if old:
            source = min(old)
        else:
            first = mine[np.argmin(np.asarray(events["t_first"], float)[mine])]
            source = conn.execute(schema.SOURCES.insert().values(
                uuid=_run_source_uuid(events, first) or str(uuid.uuid4()), name="",
                ra=float(events["ra"][first]), dec=float(events["dec"][first]),
                t_first=float(events["t_first"][first]), t_last=float(events["t_last"][first]),
                n_events=0)).inserted_primary_key[0]
            new.append(source)
        ids[mine] = source
    return ids, new


def source_of_uuid(conn, value: str):
    """The stored source a UUID names: a source's own UUID, or the ``source_uuid`` a run gave
    one of its events (the ``so_source_id`` of alerts); None if none."""
    if not value:
        return None
    found = conn.execute(sa.select(schema.SOURCES.c.id).where(
        schema.SOURCES.c.uuid == value)).scalar()
    if found is None:
        found = conn.execute(sa.select(sa.func.min(schema.EVENTS.c.source_id)).where(
            schema.EVENTS.c.source_uuid == value)).scalar()
    return found


def refresh_sources(conn, source_ids):
    """Position, span, count and name of ``source_ids`` from their stored events; a source
    without events is deleted."""
    ev = schema.EVENTS.c
    for source in sorted({int(s) for s in source_ids}):
        rows = conn.execute(sa.select(ev.ra, ev.dec, ev.pos_err, ev.t_first, ev.t_last)
                            .where(ev.source_id == source)).all()
        if not rows:
            conn.execute(schema.SOURCES.delete().where(schema.SOURCES.c.id == source))
            continue
        ra, dec, err, t0, t1 = (np.array([np.nan if v is None else v for v in col], float)
                                for col in zip(*rows))
        s_ra, s_dec, s_err = weighted_position(ra * DEG, dec * DEG, err * ARCSEC)
        s_ra, s_dec = np.degrees(s_ra), np.degrees(s_dec)
        conn.execute(schema.SOURCES.update().where(schema.SOURCES.c.id == source).values(
            ra=s_ra, dec=s_dec, pos_err=_python(s_err / ARCSEC), t_first=float(np.min(t0)),
            t_last=float(np.max(t1)), n_events=len(rows), name=event_name(s_ra, s_dec)))


def _observation_row(conn, obs_id: str, run: Run) -> tuple:
    """``(id, existed)`` of the observation's row, created or updated with the run's
    provenance."""
    prov = run.provenance
    values = dict(run_folder=run.folder, preprocess_config=prov.get("preprocess_config", ""),
                  preprocess_config_sha256=prov.get("preprocess_config_sha256", ""),
                  so_transients_version=prov.get("so_transients_version", ""),
                  ingested_utc=datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S"),
                  n_events=0, n_detections=0, n_lightcurve_points=0)
    obs = schema.OBSERVATIONS
    found = conn.execute(sa.select(obs.c.id).where(obs.c.obs_id == obs_id)).scalar()
    if found is None:
        return conn.execute(obs.insert().values(obs_id=obs_id, **values)) \
            .inserted_primary_key[0], False
    conn.execute(obs.update().where(obs.c.id == found).values(**values))
    return found, True


def _delete_owned(conn, observation_id) -> tuple:
    """Delete the rows stored with an observation; returns ``(the sources they belonged to,
    {event_uuid: id} of its events)``: a re-ingested event keeps its row id."""
    ev = schema.EVENTS.c
    stored = conn.execute(sa.select(ev.source_id, ev.event_uuid, ev.id).where(
        ev.observation_id == observation_id)).all()
    for table in schema.OWNED:
        conn.execute(table.delete().where(table.c.observation_id == observation_id))
    return {row[0] for row in stored}, {row[1]: row[2] for row in stored if row[1]}


def cutout_images(cutouts: Table, folder) -> dict:
    """``data`` (Jy, rows of pixels, None where nothing fell: lightcurvedb's ``Cutout.data``)
    and ``wcs`` (the FITS header's WCS as text) of each cutout, read from its file in the
    run's ``folder``; names the file it cannot read."""
    from astropy.io import fits
    from astropy.wcs import WCS

    data, wcs = [], []
    for name in cutouts["file"]:
        path = Path(folder) / str(name)
        try:
            with fits.open(path) as hdus:
                image, header = hdus[0].data.astype(float) / 1000.0, hdus[0].header
        except (OSError, IndexError, AttributeError) as exc:
            raise ValueError(f"{path}: cannot read the cutout: {exc}") from None
        data.append([[v if math.isfinite(v) else None for v in row] for row in image.tolist()])
        wcs.append(WCS(header).to_header_string())
    return dict(data=data, wcs=wcs)


def ingest_observation(conn, part: ObservationRows, run: Run,
                       cfg: AssociationConfig) -> IngestResult:
    """One observation's rows, inside the caller's write transaction (see the module)."""
    observation_id, existed = _observation_row(conn, part.obs_id, run)
    touched, row_ids = _delete_owned(conn, observation_id)
    ids, new = associate(conn, part.events, cfg)
    known = dict(zip(np.asarray(part.events["event_id"], int).tolist(), ids.tolist()))
    source_of = lambda event_ids: [known[int(e)] for e in event_ids]
    fixed = dict(observation_id=observation_id)
    ev = part.events
    snr = np.asarray(ev["peak_flux"], float) / np.asarray(ev["peak_flux_err"], float)
    event_rows = table_rows(ev, schema.EVENTS, fixed, dict(source_id=ids, peak_snr=snr))
    for row in event_rows:                  # stored before: its row id is kept
        if row.get("event_uuid") in row_ids:
            row["id"] = row_ids[row["event_uuid"]]
    inserts = [   # an insert's rows share their columns: events with a kept id apart
        (schema.EVENTS, [row for row in event_rows if "id" in row]),
        (schema.EVENTS, [row for row in event_rows if "id" not in row]),
        (schema.DETECTIONS, table_rows(part.detections, schema.DETECTIONS, fixed,
                                       dict(source_id=source_of(part.labels),
                                            run_event_id=part.labels))),
        (schema.LIGHTCURVE_POINTS, table_rows(part.lightcurves, schema.LIGHTCURVE_POINTS, fixed,
                                              dict(source_id=source_of(
                                                  part.lightcurves["event_id"])))),
        (schema.LIGHTCURVE_FITS, table_rows(part.fits, schema.LIGHTCURVE_FITS, fixed,
                                            dict(source_id=source_of(part.fits["event_id"])))),
        (schema.CUTOUTS, table_rows(part.cutouts, schema.CUTOUTS, fixed,
                                    dict(source_id=source_of(part.cutouts["event_id"]),
                                         **cutout_images(part.cutouts, run.folder)))),
    ]
    for table, rows in inserts:
        if rows:
            conn.execute(table.insert(), rows)
    refresh_sources(conn, touched | set(ids.tolist()))
    conn.execute(schema.OBSERVATIONS.update().where(schema.OBSERVATIONS.c.id == observation_id)
                 .values(n_events=len(ev), n_detections=len(part.detections),
                         n_lightcurve_points=len(part.lightcurves)))
    return IngestResult(part.obs_id, len(ev), len(part.detections), len(part.lightcurves),
                        len(new), existed)


def ingest_run(engine: sa.Engine, run: Run, cfg: AssociationConfig | None = None,
               on_written=None) -> list:
    """Every observation of ``run``, one transaction each, in the order of their first event;
    returns their :class:`IngestResult`. ``cfg``: the association rules against stored
    sources (default: the events' defaults). ``on_written(obs_id, conn)``: called inside
    each transaction once its rows are written, before the commit."""
    cfg = cfg or AssociationConfig()
    results = []
    check_schema(engine)        # an older database is refused, naming `db migrate`
    for part in split(run):
        with write_transaction(engine) as conn:
            result = ingest_observation(conn, part, run, cfg)
            if on_written is not None:
                on_written(part.obs_id, conn)
        log.info("%s: %d event(s), %d detection(s), %d light-curve point(s), %d new source(s)%s",
                 result.obs_id, result.events, result.detections, result.lightcurve_points,
                 result.new_sources, " (replaced)" if result.replaced else "")
        results.append(result)
    return results
