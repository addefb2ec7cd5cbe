"""Opening the database (SQLite by path or URL, PostgreSQL by URL) and its write transactions.

Writers are serialised, so two ingests running at once never interleave their association
against the stored sources:

* SQLite: every write transaction starts with ``BEGIN IMMEDIATE`` (the file's write lock is
  taken before anything is read) and a writer waits up to ``busy_timeout_s`` for the lock; the
  file is in WAL mode, so readers go on while one writer works;
* PostgreSQL: every write transaction first takes a transaction-level advisory lock
  (``pg_advisory_xact_lock``), released by its commit or rollback, also when the writer dies.

A transaction that does not commit (an exception, a killed process) leaves nothing behind.
"""
from __future__ import annotations

import weakref
import zlib
from contextlib import contextmanager
from pathlib import Path

import sqlalchemy as sa

from so_transients.database import schema

#: The advisory lock every PostgreSQL writer takes.
ADVISORY_LOCK = zlib.crc32(b"so_transients.database")

#: Engines whose schema was found current (checked once per engine).
_CHECKED = weakref.WeakSet()


def database_url(path_or_url) -> str:
    """A SQLAlchemy URL: a path becomes ``sqlite:///<absolute path>``; ``postgresql://`` uses
    psycopg (version 3)."""
    text = str(path_or_url)
    if "://" not in text:
        return f"sqlite:///{Path(text).expanduser().resolve()}"
    if text.startswith("postgresql://") or text.startswith("postgres://"):
        return "postgresql+psycopg://" + text.split("://", 1)[1]
    return text


def _sqlite_setup(engine, busy_timeout_s):
    """WAL journal, foreign keys, a busy timeout, and ``BEGIN IMMEDIATE`` for transactions
    begun on a connection with the execution option ``immediate=True``."""

    @sa.event.listens_for(engine, "connect")
    def _connect(dbapi_connection, _record):
        dbapi_connection.isolation_level = None      # SQLAlchemy's begin event says BEGIN
        cursor = dbapi_connection.cursor()
        cursor.execute(f"PRAGMA busy_timeout = {int(busy_timeout_s * 1000)}")
        cursor.execute("PRAGMA journal_mode = WAL")
        cursor.execute("PRAGMA foreign_keys = ON")
        cursor.close()

    @sa.event.listens_for(engine, "begin")
    def _begin(conn):
        immediate = conn.get_execution_options().get("immediate", False)
        conn.exec_driver_sql("BEGIN IMMEDIATE" if immediate else "BEGIN")


def open_engine(path_or_url, busy_timeout_s=120.0) -> sa.Engine:
    """An engine on the database at ``path_or_url`` (see :func:`database_url`). A SQLite file
    is created on first write; its folder must exist."""
    url = sa.make_url(database_url(path_or_url))
    if url.get_backend_name() == "sqlite":
        if url.database and url.database != ":memory:":
            folder = Path(url.database).parent
            if not folder.is_dir():
                raise FileNotFoundError(f"{url.database}: folder {folder} does not exist")
        engine = sa.create_engine(url, connect_args={"timeout": busy_timeout_s})
        _sqlite_setup(engine, busy_timeout_s)
        return engine
    if url.get_backend_name() == "postgresql":
        return sa.create_engine(url, pool_pre_ping=True)
    raise ValueError(f"{url!r}: unsupported database (use a SQLite path or sqlite:/// URL, or "
                     "postgresql+psycopg://user@host/db)")


@contextmanager
def write_transaction(engine: sa.Engine):
    """A connection in a transaction that holds the writers' lock (see the module): commits
    when the block ends, rolls back on an exception."""
    with engine.connect() as conn:
        if engine.dialect.name == "sqlite":
            conn.execution_options(immediate=True)
        with conn.begin():
            if engine.dialect.name == "postgresql":
                conn.execute(sa.text("SELECT pg_advisory_xact_lock(:key)"),
                             {"key": ADVISORY_LOCK})
            yield conn


def check_schema(engine: sa.Engine):
    """:func:`schema.check_current` on ``engine``'s database, once per engine."""
    if engine not in _CHECKED:
        with engine.connect() as conn:
            schema.check_current(conn)
        _CHECKED.add(engine)


@contextmanager
def read_connection(engine: sa.Engine):
    """A connection for queries, after checking the schema is current (once per engine)."""
    check_schema(engine)
    with engine.connect() as conn:
        yield conn


def migrate(engine: sa.Engine) -> list:
    """:func:`so_transients.database.schema.migrate` in a write transaction; returns what
    was done."""
    with write_transaction(engine) as conn:
        done = schema.migrate(conn)
    _CHECKED.add(engine)
    return done


def open_database(path_or_url, create=True) -> sa.Engine:
    """An engine on an events database checked to be current (:func:`schema.check_current`:
    an older one is refused, naming ``so-transients db migrate``); ``create``: an empty
    database gets the tables."""
    engine = open_engine(path_or_url)
    url = engine.url
    if url.get_backend_name() == "sqlite" and not Path(url.database or "").is_file() \
            and not create:
        raise FileNotFoundError(f"{url.database}: no such database file")
    if create:
        with engine.connect() as conn:
            empty = schema.stored_revision(conn) is None
        if empty:
            migrate(engine)
    check_schema(engine)
    return engine
