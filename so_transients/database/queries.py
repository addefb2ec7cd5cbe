"""Queries: events or sources by cone, time range and significance, a source's light curve,
and the row counts. Results are astropy tables with the stored columns' units and meanings
(degrees, arcsec, ctime seconds and ISO UTC, mJy); NULLs read back as NaN (floats), -1
(integers) or '' (strings), as in the events files.
"""
from __future__ import annotations

import numpy as np
import sqlalchemy as sa
from astropy.table import Table

from so_transients.common.angles import DEG, sky_separation
from so_transients.common.times import parse_time
from so_transients.database import schema
from so_transients.database.engine import read_connection
from so_transients.database.ingest import box_condition, source_of_uuid
from so_transients.database.lightcurvedb import (
    to_cutout, to_flux_measurement, to_instruments, to_source
)


def _unit_and_meaning(sql_table: sa.Table, name):
    declared = schema.DECLARED.get(sql_table.name, {}).get(name)
    if declared is not None:
        return declared.unit, declared.description
    comment = sql_table.c[name].comment or "" if name in sql_table.c else ""
    if comment.endswith("]") and "[" in comment:
        text, unit = comment[:-1].rsplit("[", 1)
        return unit, text.strip()
    return None, comment


def to_table(rows, columns, sql_table: sa.Table) -> Table:
    """An astropy table of result ``rows`` with ``columns`` (names in ``sql_table``, whose
    units and meanings they take)."""
    out = Table()
    for i, name in enumerate(columns):
        values = [row[i] for row in rows]
        col = sql_table.c[name] if name in sql_table.c else None
        python_type = None
        if col is not None and not isinstance(col.type, sa.JSON):
            python_type = col.type.python_type
        if python_type is float:
            data = np.array([np.nan if v is None else v for v in values], float)
        elif python_type is int:
            data = np.array([-1 if v is None else v for v in values], np.int64)
        elif python_type is bool:
            data = np.array([bool(v) for v in values], bool)
        elif python_type is str:
            data = np.array(["" if v is None else v for v in values], str)
        else:
            data = np.array(values + [None], object)[:-1]
        out[name] = data
        out[name].unit, out[name].description = _unit_and_meaning(sql_table, name)
    return out


def _cone_where(sql_table, cone):
    if cone is None:
        return []
    ra, dec, radius = (float(v) for v in cone)
    if not (0 < radius <= 180 and -90 <= dec <= 90):
        raise ValueError(f"cone ({ra}, {dec}, {radius}): need -90 <= dec <= 90 and "
                         "0 < radius <= 180 degrees")
    return [box_condition(sql_table, ra % 360.0, dec, radius)]


def find_events(engine, cone=None, start=None, stop=None, min_snr=None, event=None) -> Table:
    """Stored events, in time order: within ``cone`` = (ra, dec, radius) degrees, overlapping
    the time range [``start``, ``stop``] (ctime or ISO UTC; either may be None), with
    ``peak_snr`` (peak_flux / peak_flux_err) at least ``min_snr``, with ``event_uuid``
    ``event`` (an alert's ``so_event_id``). Columns: the events
    file's (``run_event_id``, ``run_source_id`` for its numbering), ``id``, ``source_id``
    (persistent), ``source_name``, ``observation`` (the obs_id it was ingested with),
    ``peak_snr``."""
    ev, src, obs = schema.EVENTS, schema.SOURCES, schema.OBSERVATIONS
    where = _cone_where(ev, cone)
    if start is not None:
        where.append(ev.c.t_last >= parse_time(start))
    if stop is not None:
        where.append(ev.c.t_first <= parse_time(stop))
    if min_snr is not None:
        where.append(ev.c.peak_snr >= float(min_snr))
    if event is not None:
        where.append(ev.c.event_uuid == str(event))
    extra = [src.c.name.label("source_name"), obs.c.obs_id.label("observation")]
    with read_connection(engine) as conn:
        query_table = ev.join(src, ev.c.source_id == src.c.id).join(
            obs, ev.c.observation_id == obs.c.id)
        columns = [c for c in ev.c if c.name != "extra"]
        rows = conn.execute(sa.select(*columns, *extra).select_from(query_table).where(*where)
                            .order_by(ev.c.t_first, ev.c.id)).all()
    rows = _in_cone(rows, [c.name for c in columns], cone)
    out = to_table([r[:len(columns)] for r in rows], [c.name for c in columns], ev)
    out["source_name"] = np.array([r[-2] for r in rows] + [""], str)[:-1]
    out["observation"] = np.array([r[-1] for r in rows] + [""], str)[:-1]
    return out


def _in_cone(rows, names, cone):
    """The ``rows`` (with ``ra``, ``dec`` among ``names``) within ``cone``."""
    if cone is None or not rows:
        return rows
    ra, dec, radius = (float(v) for v in cone)
    sep = sky_separation(np.array([r[names.index("ra")] for r in rows], float) * DEG,
                         np.array([r[names.index("dec")] for r in rows], float) * DEG,
                         ra * DEG, dec * DEG)
    return [r for r, s in zip(rows, np.atleast_1d(sep)) if s <= radius * DEG]


def find_sources(engine, cone=None, start=None, stop=None) -> Table:
    """Stored sources, by id: within ``cone`` = (ra, dec, radius) degrees, with events in
    [``start``, ``stop``] (ctime or ISO UTC)."""
    src = schema.SOURCES
    where = _cone_where(src, cone)
    if start is not None:
        where.append(src.c.t_last >= parse_time(start))
    if stop is not None:
        where.append(src.c.t_first <= parse_time(stop))
    columns = list(src.c)
    with read_connection(engine) as conn:
        rows = conn.execute(sa.select(*columns).where(*where).order_by(src.c.id)).all()
    return to_table(_in_cone(rows, [c.name for c in columns], cone), [c.name for c in columns],
                    src)


def source_row(conn, source) -> dict:
    """The stored source ``source`` as a mapping: its id, its UUID, or the ``source_uuid`` a
    run gave one of its events (an alert's ``so_source_id``)."""
    src = schema.SOURCES
    try:
        cond = src.c.id == int(source)
    except (TypeError, ValueError):
        cond = src.c.id == source_of_uuid(conn, str(source))
    row = conn.execute(sa.select(src).where(cond)).mappings().first()
    if row is None:
        raise ValueError(f"source {source}: not in the database")
    return dict(row)


def lightcurve(engine, source) -> Table:
    """The light-curve points of source ``source`` (id or UUID), in time order: the
    ``lightcurves`` file's columns (``run_event_id``, ``run_source_id`` for its numbering),
    with ``source_id`` (persistent) and ``source_uuid``. The table's ``meta`` holds the
    source's row."""
    lc = schema.LIGHTCURVE_POINTS
    columns = [c for c in lc.c if c.name not in ("extra", "observation_id")]
    with read_connection(engine) as conn:
        src = source_row(conn, source)
        rows = conn.execute(sa.select(*columns).where(lc.c.source_id == src["id"])
                            .order_by(lc.c.ctime, lc.c.bandpass, lc.c.id)).all()
    out = to_table(rows, [c.name for c in columns], lc)
    out["source_uuid"] = np.full(len(out), src["uuid"])
    out.meta["source"] = src
    return out


def flux_measurements(points: Table) -> list:
    """lightcurvedb FluxMeasurement dicts of a :func:`lightcurve` table."""
    return [to_flux_measurement(row, row["source_uuid"]) for row in points]


def lightcurvedb_records(engine, source) -> dict:
    """Everything lightcurvedb holds of source ``source`` (id or UUID), as its models define
    it: ``sources`` (one Source), ``instruments``, ``flux_measurements`` and ``cutouts``
    (each tied to the measurement of its crossing: same observation, wafer, band and time)."""
    points = lightcurve(engine, source)
    src = points.meta["source"]
    ev, cut = schema.EVENTS, schema.CUTOUTS
    with read_connection(engine) as conn:
        events = conn.execute(sa.select(ev.c.catalogue, ev.c.cat_source_id, ev.c.cat_source_name)
                              .where(ev.c.source_id == src["id"])).mappings().all()
        cutouts = conn.execute(sa.select(cut).where(cut.c.source_id == src["id"])
                               .order_by(cut.c.ctime, cut.c.bandpass)).mappings().all()
    out = []
    for c in cutouts:
        at = [p for p in points if (p["obs_id"], p["wafer_slot"], p["bandpass"]) ==
              (c["obs_id"], c["wafer_slot"], c["bandpass"]) and abs(p["ctime"] - c["ctime"]) < 1e-3]
        if at:
            out.append(to_cutout(c, at[0], src["uuid"]))
    return dict(sources=[to_source(src, events)], instruments=to_instruments(points),
                flux_measurements=flux_measurements(points), cutouts=out)


def counts(engine) -> dict:
    """{table: rows} of every stored table."""
    with read_connection(engine) as conn:
        return {t.name: conn.execute(sa.select(sa.func.count()).select_from(t)).scalar()
                for t in (schema.OBSERVATIONS, schema.SOURCES, *reversed(schema.OWNED))}


def above_snr(engine, min_snr) -> Table:
    """Events with ``peak_snr`` at least ``min_snr`` (:func:`find_events`)."""
    return find_events(engine, min_snr=min_snr)

