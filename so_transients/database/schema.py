"""The database's tables, derived from the column declarations of the tables it stores, and
its schema version with the migrations that bring an older database up to it.

Tables (SQLAlchemy Core, one :data:`METADATA`):

* ``schema_version``: one row per migration applied (version, description, UTC);
* ``observations``: one row per observation ingested (``obs_id`` unique), with where its rows
  came from (run folder, preprocess config and its digest, package version, time);
* ``sources``: the persistent sources, ``id`` kept across observations (and a UUID for
  lightcurvedb's ``source_id``), with the weighted position and time span of their events;
* ``events``, ``detections``, ``lightcurve_points``, ``lightcurve_fits``, ``cutouts``: the rows
  of one run of ``so-transients events``, each with the observation it was ingested with
  (``observation_id``) and its persistent source (``source_id``).

The last five take their columns from the declarations of the files they store:
:data:`so_transients.events.schema.EVENTS`, ``LIGHTCURVES``, ``LIGHTCURVE_FITS``, ``CUTOUTS``
(with the cutout itself in JSON, as lightcurvedb's ``Cutout`` holds it) and the
candidate schema (:data:`so_transients.common.candidates.SCHEMA`), each with its kind, unit and
meaning. The run's own numbering is kept as ``run_event_id`` and ``run_source_id``
(:data:`RENAMED`). A column added to one of those declarations needs no code here: opening the
database for writing adds it (:func:`add_missing_columns`), and until then, or for a column that
no declaration names, the value is kept in the row's JSON ``extra`` column.

A structural change is a new function appended to :data:`MIGRATIONS`; :func:`migrate` applies
those the database has not seen, in one locked transaction, and records each.
"""
from __future__ import annotations

from datetime import datetime, timezone

import sqlalchemy as sa
from sqlalchemy.dialects.postgresql import JSONB

from so_transients.common import candidates
from so_transients.common.candidates import Column
from so_transients.events import schema as event_schema

#: Run-local numbering in the events files, renamed in the database (whose ``source_id`` is
#: the persistent source).
RENAMED = {"event_id": "run_event_id", "source_id": "run_source_id"}

#: SQL type of each :class:`~so_transients.common.candidates.Column` kind.
SQL_TYPES = {"int": sa.BigInteger, "float": sa.Double, "bool": sa.Boolean, "str": sa.Text}

JSON = sa.JSON().with_variant(JSONB(), "postgresql")

METADATA = sa.MetaData()

#: The declared columns of each stored table, by database column name.
DECLARED: dict[str, dict[str, Column]] = {}


def db_name(column: Column) -> str:
    """The database name of a declared column."""
    return RENAMED.get(column.name, column.name)


def _declared(table_name, columns) -> list:
    DECLARED[table_name] = {db_name(c): c for c in columns}
    return [sa.Column(db_name(c), SQL_TYPES[c.kind](), comment=_comment(c)) for c in columns]


def _comment(column: Column) -> str:
    return f"{column.description} [{column.unit}]" if column.unit else column.description


def _owned():
    """The columns every per-observation table starts with."""
    return [sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
            sa.Column("observation_id", sa.Integer,
                      sa.ForeignKey("observations.id", ondelete="CASCADE"), nullable=False,
                      index=True, comment="the observation it was ingested with"),
            sa.Column("source_id", sa.Integer, sa.ForeignKey("sources.id"), nullable=False,
                      index=True, comment="persistent source")]


SCHEMA_VERSION = sa.Table(
    "schema_version", METADATA,
    sa.Column("version", sa.Integer, primary_key=True, autoincrement=False),
    sa.Column("description", sa.Text, nullable=False),
    sa.Column("applied_utc", sa.Text, nullable=False),
)

OBSERVATIONS = sa.Table(
    "observations", METADATA,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("obs_id", sa.Text, nullable=False, unique=True),
    sa.Column("run_folder", sa.Text, comment="events folder it was ingested from"),
    sa.Column("preprocess_config", sa.Text),
    sa.Column("preprocess_config_sha256", sa.Text),
    sa.Column("so_transients_version", sa.Text, comment="version that wrote the run"),
    sa.Column("ingested_utc", sa.Text, nullable=False),
    sa.Column("n_events", sa.Integer, nullable=False),
    sa.Column("n_detections", sa.Integer, nullable=False),
    sa.Column("n_lightcurve_points", sa.Integer, nullable=False),
)

SOURCES = sa.Table(
    "sources", METADATA,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("uuid", sa.String(36), nullable=False, unique=True,
              comment="lightcurvedb source_id"),
    sa.Column("name", sa.Text, nullable=False, comment="SOTR J... of its position"),
    sa.Column("ra", sa.Double, nullable=False, comment="weighted RA of its events [deg]"),
    sa.Column("dec", sa.Double, nullable=False, index=True,
              comment="weighted Dec of its events [deg]"),
    sa.Column("pos_err", sa.Double, comment="one-axis error of that position [arcsec]"),
    sa.Column("t_first", sa.Double, nullable=False, comment="first event's t_first [s]"),
    sa.Column("t_last", sa.Double, nullable=False, index=True,
              comment="last event's t_last [s]"),
    sa.Column("n_events", sa.Integer, nullable=False),
)

EVENTS = sa.Table(
    "events", METADATA,
    *_owned(),
    sa.Column("peak_snr", sa.Double, index=True,
              comment="peak_flux / peak_flux_err: the event's significance"),
    *_declared("events", event_schema.EVENTS),
    sa.Column("extra", JSON, comment="columns of the events file no declaration names"),
    sa.UniqueConstraint("observation_id", "run_event_id"),
    sa.Index("ix_events_dec", "dec"),
    sa.Index("ix_events_t_first", "t_first"),
)

DETECTIONS = sa.Table(
    "detections", METADATA,
    *_owned(),
    sa.Column("run_event_id", sa.BigInteger, nullable=False, comment="its event in the run"),
    *_declared("detections", [Column("obs_id", "str", None, "catalog", "observation"),
                              *candidates.columns(saved=True)]),
    sa.Column("extra", JSON, comment="columns of the detections table no declaration names"),
    sa.Index("ix_detections_t_peak", "t_peak"),
)

LIGHTCURVE_POINTS = sa.Table(
    "lightcurve_points", METADATA,
    *_owned(),
    *_declared("lightcurve_points", event_schema.LIGHTCURVES),
    sa.Column("extra", JSON, comment="columns of the light-curve file no declaration names"),
    sa.Index("ix_lightcurve_points_source_ctime", "source_id", "ctime"),
)

LIGHTCURVE_FITS = sa.Table(
    "lightcurve_fits", METADATA,
    *_owned(),
    *_declared("lightcurve_fits", event_schema.LIGHTCURVE_FITS),
    sa.Column("extra", JSON, comment="columns of the fits file no declaration names"),
    sa.UniqueConstraint("observation_id", "run_event_id", "bandpass"),
)

CUTOUTS = sa.Table(
    "cutouts", METADATA,
    *_owned(),
    *_declared("cutouts", event_schema.CUTOUTS),
    sa.Column("data", JSON, comment="the cutout in Jy, rows of pixels, null where nothing fell "
                                    "(lightcurvedb Cutout data)"),
    sa.Column("wcs", sa.Text, comment="its FITS WCS header"),
    sa.Column("extra", JSON, comment="columns of the cutouts file no declaration names"),
    sa.UniqueConstraint("observation_id", "run_event_id", "bandpass"),
)

#: The per-observation tables, in the order their rows are deleted.
OWNED = (CUTOUTS, LIGHTCURVE_FITS, LIGHTCURVE_POINTS, DETECTIONS, EVENTS)


# ----------------------------------------------------------------------------- migrations

def _create_tables(conn):
    """Version 1: every table and index (a new database gets the later versions' too)."""
    METADATA.create_all(conn)


def _catalogue_ids_as_text(conn):
    """Version 3: the cross-matched source's id as text ('' for none, was -1). SQLite keeps
    any value in any column: its rows are rewritten only."""
    stored = {c["name"]: c["type"] for c in sa.inspect(conn).get_columns("events")}
    if "cat_source_id" not in stored:
        return
    if conn.dialect.name == "postgresql":
        if isinstance(stored["cat_source_id"], sa.String):
            return            # made by this version's create_all: text already
        conn.exec_driver_sql("ALTER TABLE events ALTER COLUMN cat_source_id TYPE text USING "
                             "CASE WHEN cat_source_id = -1 THEN '' "
                             "ELSE cat_source_id::text END")
    else:
        conn.exec_driver_sql("UPDATE events SET cat_source_id = '' WHERE cat_source_id = -1")


def _create_cutouts(conn):
    """Version 2: the events' sky cutouts."""
    CUTOUTS.create(conn, checkfirst=True)


#: ``(version, description, upgrade(connection))`` in order; append, never edit.
MIGRATIONS = (
    (1, "observations, sources, events, detections, light-curve points and fits",
     _create_tables),
    (2, "cutouts: each event's sky cutout per band, made from the TOD", _create_cutouts),
    (3, "events.cat_source_id as text: socat's ids are UUIDs since socat 0.1",
     _catalogue_ids_as_text),
)
VERSION = MIGRATIONS[-1][0]


class SchemaError(RuntimeError):
    """The database is not one this version can use as it is."""


def stored_version(conn) -> int:
    """The database's schema version (0: no schema yet)."""
    if not sa.inspect(conn).has_table(SCHEMA_VERSION.name):
        return 0
    return conn.execute(sa.select(sa.func.max(SCHEMA_VERSION.c.version))).scalar() or 0


def migrate(conn) -> list:
    """Bring the database of ``conn`` (inside a write transaction, see
    :func:`so_transients.database.engine.write_transaction`) to :data:`VERSION`, then add the
    declared columns it lacks; returns what was done (one line each). Refuses a database of a
    newer version."""
    done = []
    version = stored_version(conn)
    if version > VERSION:
        raise SchemaError(f"{conn.engine.url!r}: schema version {version} is newer than this "
                          f"so_transients knows ({VERSION}): upgrade so_transients")
    for number, description, upgrade in MIGRATIONS:
        if number > version:
            upgrade(conn)
            conn.execute(SCHEMA_VERSION.insert().values(
                version=number, description=description,
                applied_utc=datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")))
            done.append(f"schema version {number}: {description}")
    done += add_missing_columns(conn)
    return done


def missing_columns(conn) -> list:
    """``(table, column)`` of the declared columns the database's tables lack."""
    inspector = sa.inspect(conn)
    missing = []
    for name in DECLARED:
        have = {c["name"] for c in inspector.get_columns(name)}
        missing += [(METADATA.tables[name], col) for col in METADATA.tables[name].columns
                    if col.name not in have]
    return missing


def add_missing_columns(conn) -> list:
    """``ALTER TABLE ... ADD COLUMN`` for each declared column the database lacks (a column
    added to an events or candidate declaration since the database was made)."""
    quote = conn.dialect.identifier_preparer.quote
    done = []
    for table, col in missing_columns(conn):
        conn.exec_driver_sql(f"ALTER TABLE {quote(table.name)} ADD COLUMN {quote(col.name)} "
                             f"{col.type.compile(dialect=conn.dialect)}")
        done.append(f"added column {table.name}.{col.name}")
    return done


def check_current(conn):
    """Raise :class:`SchemaError` unless the database is at :data:`VERSION` with every
    declared column (what the queries need)."""
    version = stored_version(conn)
    if version == 0:
        raise SchemaError(f"{conn.engine.url!r} holds no so_transients events database "
                          "(no schema_version table): ingest a run first")
    if version != VERSION or missing_columns(conn):
        raise SchemaError(f"{conn.engine.url!r}: schema version {version} (this so_transients: "
                          f"{VERSION}) or columns missing: run `so-transients db migrate`")
