"""The database's tables, derived from the column declarations of the tables it stores, and
the migrations (alembic's) that bring an older database up to them.

Tables (SQLAlchemy Core, one :data:`METADATA`):

* ``alembic_version``: the schema's revision (alembic's own table);
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
(:data:`RENAMED`). A column added to one of those declarations needs no code here:
``so-transients db migrate`` adds it (:func:`add_missing_columns`); until then the database is
refused, with a message naming that command, and a column that no declaration names is kept in
the row's JSON ``extra`` column.

A structural change is a new alembic revision in ``migrations/versions/``; :func:`migrate` runs
those the database has not seen (``alembic upgrade head``) in one locked transaction. A database
made by the package's own runner before alembic (a ``schema_version`` table) is stamped with its
revision first.
"""
from __future__ import annotations

from pathlib import Path

import sqlalchemy as sa
from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
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

MIGRATIONS = Path(__file__).resolve().parent / "migrations"

#: the table the package's own migration runner kept before alembic (versions 1-3)
LEGACY_VERSION_TABLE = "schema_version"


class SchemaError(RuntimeError):
    """The database is not one this version can use as it is."""


def alembic_config(conn=None) -> Config:
    """alembic's config for the revisions in ``migrations/``, running on ``conn``."""
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.attributes["connection"] = conn
    return cfg


#: the revisions this version of the package knows, oldest first (read once), and the newest,
#: which it writes
REVISIONS = tuple(reversed(list(ScriptDirectory.from_config(alembic_config()).walk_revisions())))
HEAD = REVISIONS[-1].revision


def stored_revision(conn) -> str | None:
    """The database's revision (``'0003'``...; None: no schema yet). A database the
    package's own runner made reads as the revision of its last version."""
    revision = MigrationContext.configure(conn).get_current_revision()
    if revision is None and sa.inspect(conn).has_table(LEGACY_VERSION_TABLE):
        version = conn.exec_driver_sql(f"SELECT max(version) FROM {LEGACY_VERSION_TABLE}")
        return f"{version.scalar() or 0:04d}"
    return revision


def _refuse_unknown(conn, revision):
    if revision is not None and revision not in {r.revision for r in REVISIONS}:
        raise SchemaError(f"{conn.engine.url!r}: schema revision {revision} is newer than this "
                          f"so_transients knows ({HEAD}): upgrade so_transients")


def migrate(conn) -> list:
    """Bring the database of ``conn`` (inside a write transaction, see
    :func:`so_transients.database.engine.write_transaction`) to :data:`HEAD`, then add the
    declared columns it lacks; returns what was done (one line each). Refuses a database of a
    revision this version does not know (a newer one)."""
    before = stored_revision(conn)
    _refuse_unknown(conn, before)
    cfg = alembic_config(conn)
    if before is not None and MigrationContext.configure(conn).get_current_revision() is None:
        command.stamp(cfg, before)              # made by the package's own runner
    command.upgrade(cfg, "head")
    done = [f"schema revision {r.revision}: {r.doc}" for r in REVISIONS
            if before is None or int(r.revision) > int(before)]
    return done + add_missing_columns(conn)


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
    """Raise :class:`SchemaError` unless the database is at :data:`HEAD` with every declared
    column (what ingest and the queries need)."""
    revision = stored_revision(conn)
    if revision is None:
        raise SchemaError(f"{conn.engine.url!r} holds no so_transients events database "
                          "(no alembic_version table): ingest a run first")
    _refuse_unknown(conn, revision)
    if revision != HEAD or missing_columns(conn):
        raise SchemaError(f"{conn.engine.url!r}: schema revision {revision} (this so_transients: "
                          f"{HEAD}) or columns missing: run `so-transients db migrate`")
