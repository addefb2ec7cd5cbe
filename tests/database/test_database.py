"""The events database on SQLite and PostgreSQL: ingest (idempotent, association with stored
sources, concurrent writers, interrupted ingests), queries, the CLI, lightcurvedb fields and
schema migrations. Runs are simulated at the table level (:mod:`so_transients.database
.synthetic`) and written as ``so-transients events`` writes them."""
import json
import os
import signal
import subprocess
import sys
import time
import uuid
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa
from astropy.table import Table
from astropy.time import Time

from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext

from so_transients.database import schema
from so_transients.database.command import get_parser, main
from so_transients.database.engine import open_database, open_engine, write_transaction
from so_transients.database.ingest import ingest_run
from so_transients.database.lightcurvedb import (
    FIELDS, INSTRUMENT_FIELDS, SOURCE_FIELDS, from_flux_measurement
)
from so_transients.database.queries import (
    counts, find_events, find_sources, flux_measurements, lightcurve
)
from so_transients.database.runs import read_run, split
from so_transients.database.synthetic import Flare, simulated_run, write_run

REPO = Path(__file__).resolve().parents[2]
T0 = 1_700_000_000.0
HOUR = 3600.0
#: A source that flares in several observations.
P = (150.0, -20.0)


def db(*argv) -> int:
    """``so-transients db ARGV`` through the command's own parser and main."""
    return main(get_parser().parse_args([str(a) for a in argv]))


def night(prefix, start, n_obs, seed, flaring=P):
    """A run of ``n_obs`` hour-long observations from ``start``: each with a flare of the
    source at ``flaring`` and one flare at a position of its own."""
    rng = np.random.default_rng(seed)
    obs = []
    for k in range(n_obs):
        own = Flare(rng.uniform(0, 360), rng.uniform(-70, 10), 40, 700.0)
        obs.append((f"{prefix}_{k}", start + k * HOUR, [Flare(*flaring, 10 + k), own]))
    return simulated_run(obs, seed=seed, fit=False)


def stored(url) -> dict:
    return counts(open_database(url, create=False))


def source_at(url, position, radius=0.01):
    found = find_sources(open_database(url, create=False), (*position, radius))
    assert len(found) == 1, f"{len(found)} sources at {position}"
    return found[0]


def content(url) -> dict:
    """What the database holds, without its row ids: comparable between databases."""
    engine = open_database(url, create=False)
    events = find_events(engine)
    sources = find_sources(engine)
    name_of = dict(zip(sources["id"], sources["name"]))
    with engine.connect() as conn:
        obs = sorted(conn.execute(sa.select(schema.OBSERVATIONS.c.obs_id,
                                            schema.OBSERVATIONS.c.n_events,
                                            schema.OBSERVATIONS.c.n_detections,
                                            schema.OBSERVATIONS.c.n_lightcurve_points)).all())
    return dict(observations=obs,
                sources=sorted(zip(sources["name"], sources["n_events"])),
                events=sorted((o, int(e), name_of[s]) for o, e, s in
                              zip(events["observation"], events["run_event_id"],
                                  events["source_id"])))


def test_ingesting_a_run_twice_gives_the_same_rows(new_db, tmp_path):
    url = new_db()
    run = night("obs", T0, 3, seed=1)
    folder = write_run(run, tmp_path / "run")
    assert db("ingest", "--db", url, folder) == 0
    first, first_content = stored(url), content(url)
    assert first == {"observations": 3, "sources": 4, "events": 6, "detections": 24,
                     "lightcurve_points": len(run.lightcurves), "lightcurve_fits": 0,
                     "cutouts": 0}    # a synthetic run: no cutouts.ecsv, as an older folder
    def ids():
        engine = open_database(url, create=False)
        events, sources = find_events(engine), find_sources(engine)
        return (sorted(zip(events["event_uuid"], events["id"], events["source_id"])),
                sorted(zip(sources["uuid"], sources["id"])))

    first_ids = ids()
    assert db("ingest", "--db", url, folder) == 0
    assert stored(url) == first
    assert content(url) == first_content
    assert ids() == first_ids          # row ids and UUIDs kept (PostgreSQL's sequences too)


def test_a_later_observation_of_a_flaring_source_joins_its_id(new_db, tmp_path):
    url = new_db()
    first = night("n1", T0, 2, seed=2)
    db("ingest", "--db", url, write_run(first, tmp_path / "n1"))
    source = source_at(url, P)
    assert source["n_events"] == 2
    # the next night, 20 h after the last event: within source_gap_hours (24)
    db("ingest", "--db", url, write_run(night("n2", T0 + 21 * HOUR, 1, seed=3), tmp_path / "n2"))
    again = source_at(url, P)
    assert again["id"] == source["id"] and again["uuid"] == source["uuid"]
    assert again["n_events"] == 3
    points = lightcurve(open_database(url, create=False), source["id"])
    assert set(points["obs_id"]) == {"n1_0", "n1_1", "n2_0"}
    assert np.all(np.diff(points["ctime"]) >= 0)
    # the other flares are sources of their own
    assert stored(url)["sources"] == 1 + 3
    # three days after its last event: beyond source_gap_hours, a new source ...
    db("ingest", "--db", url, write_run(night("n5", T0 + 96 * HOUR, 1, seed=4), tmp_path / "n5"))
    assert len(find_sources(open_database(url, create=False), (*P, 0.01))) == 2
    # ... unless the database is told sources live longer
    url2 = new_db()
    for name in ("n1", "n5"):
        db("ingest", "--db", url2, "--source-gap-hours", 1000, tmp_path / name)
    assert source_at(url2, P)["n_events"] == 3


CONCURRENT = """
import sys, time
from pathlib import Path
from so_transients.database.engine import open_database
from so_transients.database.ingest import ingest_run
from so_transients.database.runs import read_run
url, folder, ready, go = sys.argv[1:]
run = read_run(folder)
engine = open_database(url)
Path(ready).touch()
while not Path(go).exists():
    time.sleep(0.01)
start = time.time()
ingest_run(engine, run, on_written=lambda obs, conn: time.sleep(0.2))
print(start, time.time())
"""


def test_two_concurrent_ingests_lose_and_duplicate_nothing(new_db, tmp_path):
    """Two processes ingest two runs at once, both with the same flaring source, into a new
    database: the result is that of ingesting one after the other."""
    runs = [write_run(night(f"w{k}", T0 + k * HOUR / 2, 5, seed=10 + k), tmp_path / f"w{k}")
            for k in range(2)]
    url = new_db()
    go = tmp_path / "go"
    procs = [subprocess.Popen([sys.executable, "-c", CONCURRENT, url, str(folder),
                               str(tmp_path / f"ready{k}"), str(go)], cwd=REPO,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for k, folder in enumerate(runs)]
    try:
        deadline = time.time() + 300
        while not all((tmp_path / f"ready{k}").exists() for k in range(2)):
            if time.time() > deadline or any(p.poll() is not None for p in procs):
                for p in procs:     # they wait for `go`: end them before reading what they said
                    p.kill()
                pytest.fail(f"the ingests did not start: {[p.communicate() for p in procs]}")
            time.sleep(0.05)
        go.touch()
        spans = []
        for p in procs:
            out, err = p.communicate(timeout=300)
            assert p.returncode == 0, err
            spans.append([float(v) for v in out.split()])
    finally:
        for p in procs:
            p.kill()
            p.wait()
    assert max(s[0] for s in spans) < min(s[1] for s in spans), "the ingests did not overlap"
    reference = new_db()
    for folder in runs:
        db("ingest", "--db", reference, folder)
    assert stored(url) == stored(reference)
    assert stored(url)["events"] == 20 and stored(url)["observations"] == 10
    assert source_at(url, P)["n_events"] == 10
    assert content(url)["sources"] == content(reference)["sources"]


KILLED = """
import os, signal, sys
from so_transients.database.engine import open_database
from so_transients.database.ingest import ingest_run
from so_transients.database.runs import read_run
url, folder, victim = sys.argv[1:]

def die(obs_id, conn):
    if obs_id == victim:
        os.kill(os.getpid(), signal.SIGKILL)

ingest_run(open_database(url), read_run(folder), on_written=die)
"""


def test_an_ingest_killed_half_way_then_rerun_is_complete(new_db, tmp_path):
    run = night("k", T0, 4, seed=20)
    folder = write_run(run, tmp_path / "run")
    parts = split(run)
    victim = parts[2].obs_id
    url = new_db()
    proc = subprocess.run([sys.executable, "-c", KILLED, url, str(folder), victim], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    # the two observations before the victim are stored whole, nothing of the victim's
    done = stored(url)
    assert done["observations"] == 2
    assert done["events"] == sum(len(p.events) for p in parts[:2])
    assert done["detections"] == sum(len(p.detections) for p in parts[:2])
    assert done["lightcurve_points"] == sum(len(p.lightcurves) for p in parts[:2])
    assert done["sources"] == 3
    assert db("ingest", "--db", url, folder) == 0
    reference = new_db()
    db("ingest", "--db", reference, folder)
    assert stored(url) == stored(reference)
    assert content(url) == content(reference)


def test_a_failure_inside_the_transaction_leaves_nothing_of_that_observation(new_db, tmp_path):
    run = night("f", T0, 3, seed=30)
    url = new_db()
    engine = open_database(url)
    second = split(run)[1].obs_id

    def fail(obs_id, conn):
        if obs_id == second:
            raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        ingest_run(engine, run, on_written=fail)
    assert stored(url)["observations"] == 1 and stored(url)["events"] == 2
    ingest_run(engine, run)
    assert stored(url)["observations"] == 3 and stored(url)["events"] == 6
    assert source_at(url, P)["n_events"] == 3


def test_queries_by_cone_time_and_significance(new_db, tmp_path):
    url = new_db()
    obs = [("q0", T0, [Flare(*P, 10, 1000.0), Flare(359.999, 0.0, 20, 400.0)]),
           ("q1", T0 + HOUR, [Flare(*P, 12, 2000.0), Flare(0.001, 0.001, 30, 1200.0)]),
           ("q2", T0 + 2 * HOUR, [Flare(80.0, -85.0, 40, 800.0)])]
    run = simulated_run(obs, seed=40)
    db("ingest", "--db", url, write_run(run, tmp_path / "run"))
    engine = open_database(url, create=False)
    everything = find_events(engine)
    assert len(everything) == 5
    assert everything["ra"].unit == "deg" and everything["peak_flux"].unit == "mJy"
    assert np.all(np.diff(everything["t_first"]) >= 0)
    # a cone across RA 0 holds the two flares either side of it, as one source
    across = find_events(engine, cone=(0.0, 0.0, 0.05))
    assert len(across) == 2 and len(set(across["source_id"])) == 1
    assert len(find_events(engine, cone=(*P, 0.01))) == 2
    assert len(find_events(engine, cone=(*P, 1.0))) == 2
    assert len(find_events(engine, cone=(80.0 + 20.0, -85.0, 2.0))) == 1   # near the pole
    assert len(find_events(engine, cone=(P[0] + 1.0, P[1], 0.5))) == 0
    # time range: ctime or ISO UTC, events overlapping it
    hour1 = find_events(engine, start=T0 + HOUR, stop=T0 + 2 * HOUR - 1)
    assert set(hour1["observation"]) == {"q1"}
    iso = find_events(engine, start="2023-11-14T23:13:20", stop="2023-11-15T00:13:19")
    assert list(iso["id"]) == list(hour1["id"])
    assert len(find_events(engine, start=T0 + 2 * HOUR)) == 1
    # significance: peak_flux / peak_flux_err
    snr = everything["peak_flux"] / everything["peak_flux_err"]
    strong = find_events(engine, min_snr=30)
    assert sorted(strong["id"]) == sorted(everything["id"][snr >= 30])
    assert 0 < len(strong) < len(everything)
    assert len(find_events(engine, cone=(*P, 0.01), start=T0 + HOUR, min_snr=30)) == 1
    # a source's light curve: every point of its events, both observations
    source = source_at(url, P)
    points = lightcurve(engine, source["id"])
    at_p = run.events["event_id"][np.abs(run.events["ra"] - P[0]) < 0.01]
    assert len(points) == np.isin(run.lightcurves["event_id"], at_p).sum() > 0
    assert set(points["obs_id"]) == {"q0", "q1"} and points["flux"].unit == "mJy"
    assert np.sum(points["detected"]) == 8
    assert len(lightcurve(engine, source["uuid"])) == len(points)
    with pytest.raises(ValueError, match="not in the database"):
        lightcurve(engine, 10_000)


def test_the_command_writes_tables_and_lightcurvedb_json(new_db, tmp_path, capsys):
    url = new_db()
    db("ingest", "--db", url, write_run(night("c", T0, 2, seed=50), tmp_path / "run"))
    capsys.readouterr()
    assert db("query", "--db", url, "--cone", *P, 0.01) == 0
    assert capsys.readouterr().out.strip().endswith("2 event(s)")
    out = tmp_path / "events.ecsv"
    assert db("query", "--db", url, "--start", "2023-11-14T22:13:20", "--min-snr", 5,
              "-o", out) == 0
    table = Table.read(out)
    assert len(table) == 4 and table["ra"].unit == "deg"
    with pytest.raises(FileExistsError):
        db("query", "--db", url, "-o", out)
    assert db("query", "--db", url, "--sources", "-o", tmp_path / "sources.csv") == 0
    assert len(Table.read(tmp_path / "sources.csv", format="ascii.csv", comment="#")) == 3
    source = source_at(url, P)
    assert db("lightcurve", "--db", url, source["id"], "--lightcurvedb",
              "-o", tmp_path / "lc.json") == 0
    records = json.loads((tmp_path / "lc.json").read_text())
    measurements = records["flux_measurements"]
    points = lightcurve(open_database(url, create=False), source["id"])
    assert len(measurements) == len(points)
    assert all(set(m) == set(FIELDS) and m["source_id"] == source["uuid"]
               for m in measurements)
    (src,) = records["sources"]
    assert tuple(src) == SOURCE_FIELDS and src["source_id"] == source["uuid"]
    assert -180 <= src["ra"] < 180 and src["dec"] == pytest.approx(source["dec"])
    assert [(i["frequency"], i["module"]) for i in records["instruments"]] == sorted(
        {(int(p["frequency"]), str(p["module"])) for p in points})
    assert all(tuple(i) == INSTRUMENT_FIELDS for i in records["instruments"])
    assert records["cutouts"] == []          # a synthetic run: no cutouts
    assert db("lightcurve", "--db", url, source["id"], "-o", tmp_path / "lc.fits") == 0
    assert len(Table.read(tmp_path / "lc.fits")) == len(measurements)
    with pytest.raises(FileNotFoundError):
        db("query", "--db", str(tmp_path / "none.db"))
    with pytest.raises(ValueError, match="--detections goes with one"):
        db("ingest", "--db", url, "--detections", out, tmp_path / "run", tmp_path / "run")


def test_light_curve_points_round_trip_through_lightcurvedb_fields(new_db, tmp_path):
    url = new_db()
    run = night("l", T0, 2, seed=60)
    db("ingest", "--db", url, write_run(run, tmp_path / "run"))
    engine = open_database(url, create=False)
    points = lightcurve(engine, source_at(url, P)["id"])
    measurements = flux_measurements(points)
    for m, point in zip(measurements, points):
        assert tuple(m) == FIELDS
        assert isinstance(m["measurement_id"], uuid.UUID)
        assert isinstance(m["source_id"], uuid.UUID) and str(m["source_id"]) == point["source_uuid"]
        assert isinstance(m["time"], datetime) and m["time"].utcoffset().total_seconds() == 0
        assert isinstance(m["frequency"], int) and m["frequency"] in (90, 150)
        assert -180 <= m["ra"] < 180
        assert m["flux"] == pytest.approx(point["flux"] / 1000.0)          # Jy
        assert m["extra"] == {"flags": []}            # quality flags: lightview hides a flagged point
        back = from_flux_measurement(m)
        for key in ("bandpass", "module", "frequency"):
            assert back[key] == point[key], key
        # datetime holds microseconds: the ISO time (to the ms) within one ms
        assert abs(Time(back["time"]).unix - Time(point["time"]).unix) <= 1.0001e-3
        for key in ("ctime", "ra", "dec", "ra_uncertainty", "dec_uncertainty", "flux",
                    "flux_err", "snr"):
            assert back[key] == pytest.approx(point[key], rel=1e-12, abs=1e-6), key
    assert len({m["measurement_id"] for m in measurements}) == len(measurements)
    # the same points ingested again keep their measurement ids
    db("ingest", "--db", url, tmp_path / "run")
    again = flux_measurements(lightcurve(engine, source_at(url, P)["id"]))
    assert [m["measurement_id"] for m in again] == [m["measurement_id"] for m in measurements]


def test_undeclared_columns_are_kept_and_declared_ones_are_added(new_db, tmp_path):
    """An events file with a column no declaration names (a cross-match, say) keeps it in
    ``extra``; a database lacking a declared column is refused by the queries until migrated,
    which adds it."""
    url = new_db()
    run = night("x", T0, 1, seed=70)
    run.events["catalog_name"] = [f"SRC {i}" for i in range(len(run.events))]
    run.events["catalog_separation"] = np.linspace(1.0, 2.0, len(run.events))
    engine = open_database(url)
    ingest_run(engine, run)
    with engine.connect() as conn:
        extra = [row[0] for row in conn.execute(sa.select(schema.EVENTS.c.extra)
                                                .order_by(schema.EVENTS.c.run_event_id))]
    assert [e["catalog_name"] for e in extra] == ["SRC 0", "SRC 1"]
    assert [e["catalog_separation"] for e in extra] == [1.0, 2.0]
    with write_transaction(engine) as conn:
        conn.exec_driver_sql("ALTER TABLE events DROP COLUMN note")
    with pytest.raises(schema.SchemaError, match="migrate"):
        find_events(open_engine(url))      # as another process (the check is per engine)
    assert db("migrate", "--db", url) == 0
    assert len(find_events(open_engine(url))) == 2
    with write_transaction(engine) as conn:
        assert schema.migrate(conn) == []
        assert schema.stored_revision(conn) == schema.HEAD
        conn.exec_driver_sql("UPDATE alembic_version SET version_num = '9999'")
    with pytest.raises(schema.SchemaError, match="newer"):
        open_database(url)
    with pytest.raises(schema.SchemaError, match="newer"):
        db("migrate", "--db", url)


def revision_1_database(url):
    """A database as revision 0001 made it (no cutouts table; catalogue ids as integers, -1
    for none), holding one observation, one source and two events (ids -1 and 17)."""
    engine = open_engine(url)
    with write_transaction(engine) as conn:
        command.upgrade(schema.alembic_config(conn), "0001")
        obs = conn.execute(schema.OBSERVATIONS.insert().values(
            obs_id="o1", ingested_utc="2026-12-01T00:00:00", n_events=2, n_detections=0,
            n_lightcurve_points=0)).inserted_primary_key[0]
        src = conn.execute(schema.SOURCES.insert().values(
            uuid=str(uuid.uuid4()), name="SOTR J1", ra=1.0, dec=2.0, t_first=T0, t_last=T0,
            n_events=2)).inserted_primary_key[0]
        for k, cat_id in enumerate((-1, 17)):
            conn.exec_driver_sql("INSERT INTO events (observation_id, source_id, run_event_id, "
                                 f"cat_source_id) VALUES ({obs}, {src}, {k}, {cat_id})")
    return engine


def test_a_database_of_revision_1_is_refused_until_migrated_and_then_current(new_db):
    """A database as the first schema made it is refused by ingest and the queries, naming
    ``so-transients db migrate``; migrating keeps its rows, makes the cutouts table and the
    catalogue ids text ('' for none), and leaves the tables exactly as declared."""
    url = new_db()
    revision_1_database(url)
    with pytest.raises(schema.SchemaError, match="schema revision 0001.*db migrate"):
        open_database(url)
    with pytest.raises(schema.SchemaError, match="db migrate"):
        ingest_run(open_engine(url), night("v", T0, 1, seed=71))
    assert db("migrate", "--db", url) == 0
    engine = open_database(url)
    with engine.connect() as conn:
        assert schema.stored_revision(conn) == schema.HEAD
        assert sa.inspect(conn).has_table("cutouts")
        ids = conn.exec_driver_sql("SELECT cat_source_id FROM events ORDER BY run_event_id")
        assert [str(v) for (v,) in ids] == ["", "17"]
        assert compare_metadata(MigrationContext.configure(conn), schema.METADATA) == []
    assert counts(engine)["events"] == 2 and counts(engine)["cutouts"] == 0


def test_the_revisions_build_the_declared_tables(new_db):
    """A new database, made by alembic's revisions (and the declared columns added since the
    last one), is what the package declares, as alembic's own comparison sees it."""
    url = new_db()
    engine = open_database(url)
    with engine.connect() as conn:
        assert MigrationContext.configure(conn).get_current_revision() == schema.HEAD
        assert compare_metadata(MigrationContext.configure(conn), schema.METADATA) == []


def test_a_database_of_the_packages_own_runner_is_taken_over_by_alembic(new_db):
    """A database the package's migration runner made before alembic (its ``schema_version``
    table at version 3) is stamped at revision 0003 and brought to the head; the old table
    goes."""
    url = new_db()
    engine = open_engine(url)
    with write_transaction(engine) as conn:
        command.upgrade(schema.alembic_config(conn), "0003")
        conn.exec_driver_sql("DROP TABLE alembic_version")
        conn.exec_driver_sql("CREATE TABLE schema_version (version INTEGER PRIMARY KEY, "
                             "description TEXT NOT NULL, applied_utc TEXT NOT NULL)")
        for v in (1, 2, 3):
            conn.exec_driver_sql(f"INSERT INTO schema_version VALUES ({v}, 'v{v}', '2026')")
        assert schema.stored_revision(conn) == "0003"
    with pytest.raises(schema.SchemaError, match="db migrate"):
        open_database(url)
    assert db("migrate", "--db", url) == 0
    with open_engine(url).connect() as conn:
        assert schema.stored_revision(conn) == schema.HEAD
        assert not sa.inspect(conn).has_table("schema_version")


def test_a_run_whose_detections_do_not_give_its_events_is_refused(new_db, tmp_path):
    folder = write_run(night("r", T0, 2, seed=80), tmp_path / "run")
    other = write_run(night("s", T0, 3, seed=81), tmp_path / "other")
    with pytest.raises(ValueError, match="give 6 event"):
        read_run(folder, detections=other / "detections.ecsv")
    os.remove(folder / "detections.ecsv")
    with pytest.raises(FileNotFoundError, match="give the detections table"):
        read_run(folder)
    url = new_db()
    with pytest.raises(ValueError):
        db("ingest", "--db", url, "--detections", other / "detections.ecsv", folder)
    assert not Path(url).exists() or stored(url)["observations"] == 0


def test_a_killed_test_session_leaves_no_postgres_server(tmp_path):
    """The process that started the server is killed (SIGKILL: no clean-up of its own): the
    watchdog stops the server and removes its folder."""
    script = ("from so_transients.database.server import temporary_postgres\n"
              "import sys, time\n"
              "with temporary_postgres() as url:\n"
              "    print(url, flush=True)\n"
              "    time.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    url = proc.stdout.readline().strip()
    engine = sa.create_engine(url)
    with engine.connect() as conn:
        folder = Path(conn.exec_driver_sql("SHOW data_directory").scalar()).parent
    engine.dispose()
    assert folder.is_dir()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    deadline = time.time() + 60
    while folder.exists() and time.time() < deadline:
        time.sleep(0.5)
    assert not folder.exists()
    with pytest.raises(sa.exc.OperationalError):
        with sa.create_engine(url).connect():
            pass
