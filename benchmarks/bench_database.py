"""Benchmark: the events database under load, on SQLite and PostgreSQL.

    python benchmarks/bench_database.py                     # 1,000 observations, both back ends
    python benchmarks/bench_database.py --observations 200 --backends sqlite
    python benchmarks/bench_database.py --json out.json     # also write the figures as JSON

Simulates (not timed) runs of ``so-transients events`` at the table level
(:mod:`so_transients.database.synthetic`): ``--per-run`` hour-long observations a night, each
with ``--flares`` flares detected in both MF bands at two crossings, one of them from a
population of ``--recurring`` sources that flare again on later nights (joining their stored
source when within ``source_gap_hours``), the others at new positions; light curves from 5
crossings before to 5 after, eq. 1 fitted. Then, per back end, into a new database:

1. ingest every run (one transaction per observation, association against the stored
   sources): time, observations a second, rows stored, size on disk (SQLite: the file after a
   WAL checkpoint; PostgreSQL: ``pg_database_size``);
2. ingest the first night again (replacing its rows): time;
3. 100 cone searches of 0.1 deg, and 100 source light curves: median time each.

PostgreSQL is a server started for the run (:func:`so_transients.database.server
.temporary_postgres`, default settings: fsync on) on this machine.
"""
import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "passive")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import sqlalchemy as sa  # noqa: E402

from so_transients.database.engine import open_database  # noqa: E402
from so_transients.database.ingest import ingest_run  # noqa: E402
from so_transients.database.queries import counts, find_events, lightcurve  # noqa: E402
from so_transients.database.server import temporary_postgres  # noqa: E402
from so_transients.database.synthetic import Flare, simulated_run  # noqa: E402

T0 = 1_700_000_000.0
DAY, HOUR = 86400.0, 3600.0


def make_runs(n_obs, per_run, flares, recurring, seed):
    """The simulated nights (a list of runs) and the recurring sources' positions."""
    rng = np.random.default_rng(seed)
    population = np.c_[rng.uniform(0, 360, recurring),
                       np.degrees(np.arcsin(rng.uniform(-1, np.sin(np.radians(20)), recurring)))]
    runs = []
    for night in range(int(np.ceil(n_obs / per_run))):
        observations = []
        for k in range(min(per_run, n_obs - night * per_run)):
            ra, dec = population[rng.integers(recurring)]
            scans = rng.choice(np.arange(10, 290, 15), flares, replace=False)
            obs_flares = [Flare(ra, dec, int(scans[0]), rng.uniform(400, 3000))]
            for scan in scans[1:]:
                obs_flares.append(Flare(rng.uniform(0, 360),
                                        np.degrees(np.arcsin(rng.uniform(-1, 0.35))),
                                        int(scan), rng.uniform(400, 3000)))
            observations.append((f"obs_{night:04d}_{k:02d}", T0 + night * DAY + k * HOUR,
                                 obs_flares))
        runs.append(simulated_run(observations, seed=seed + night, fit=True))
    return runs, population


def disk_size(engine) -> int:
    """Bytes the database takes on disk."""
    if engine.dialect.name == "sqlite":
        with engine.connect() as conn:
            conn.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)")
        path = Path(engine.url.database)
        return sum(p.stat().st_size for p in (path, Path(f"{path}-wal"), Path(f"{path}-shm"))
                   if p.exists())
    with engine.connect() as conn:
        return conn.execute(sa.text("SELECT pg_database_size(current_database())")).scalar()


def measure(url, runs, population, rng) -> dict:
    engine = open_database(url)
    t0 = time.perf_counter()
    for run in runs:
        ingest_run(engine, run)
    ingest_s = time.perf_counter() - t0
    rows = counts(engine)
    t0 = time.perf_counter()
    ingest_run(engine, runs[0])
    again_s = time.perf_counter() - t0
    assert counts(engine) == rows, "re-ingesting a night changed the row counts"
    cone_s, lc_s = [], []
    for ra, dec in population[rng.integers(len(population), size=100)]:
        t0 = time.perf_counter()
        found = find_events(engine, cone=(ra, dec, 0.1))
        cone_s.append(time.perf_counter() - t0)
        if len(found):
            t0 = time.perf_counter()
            lightcurve(engine, int(found["source_id"][0]))
            lc_s.append(time.perf_counter() - t0)
    out = dict(observations=rows["observations"], rows=rows, total_rows=sum(rows.values()),
               ingest_s=ingest_s, obs_per_s=rows["observations"] / ingest_s,
               reingest_night_s=again_s, size_mb=disk_size(engine) / 2**20,
               cone_ms=1e3 * float(np.median(cone_s)),
               lightcurve_ms=1e3 * float(np.median(lc_s)) if lc_s else float("nan"))
    engine.dispose()
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--observations", type=int, default=1000)
    parser.add_argument("--per-run", type=int, default=10, help="observations a night (run)")
    parser.add_argument("--flares", type=int, default=4, help="flares an observation")
    parser.add_argument("--recurring", type=int, default=200,
                        help="sources that flare again on later nights")
    parser.add_argument("--backends", nargs="+", default=["sqlite", "postgresql"],
                        choices=["sqlite", "postgresql"])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", help="also write the figures here")
    args = parser.parse_args(argv)

    t0 = time.perf_counter()
    runs, population = make_runs(args.observations, args.per_run, args.flares, args.recurring,
                                 args.seed)
    print(f"simulated {args.observations} observations in {len(runs)} runs "
          f"({time.perf_counter() - t0:.0f} s, not timed below)", flush=True)
    results = {}
    for backend in args.backends:
        rng = np.random.default_rng(args.seed)
        if backend == "sqlite":
            with tempfile.TemporaryDirectory() as folder:
                results[backend] = measure(str(Path(folder) / "bench.db"), runs, population,
                                           rng)
        else:
            with temporary_postgres() as server:
                admin = sa.create_engine(server, isolation_level="AUTOCOMMIT")
                with admin.connect() as conn:
                    conn.exec_driver_sql("CREATE DATABASE bench")
                admin.dispose()
                results[backend] = measure(sa.make_url(server).set(database="bench")
                                           .render_as_string(hide_password=False),
                                           runs, population, rng)
        print(f"{backend}: done", flush=True)

    names = list(next(iter(results.values()))["rows"])
    header = ["back end", "obs", "ingest (s)", "obs/s", "re-ingest night (s)", "size (MB)",
              "cone (ms)", "light curve (ms)", *names]
    print("\n| " + " | ".join(header) + " |\n|" + " --- |" * len(header))
    for backend, r in results.items():
        cells = [backend, r["observations"], f"{r['ingest_s']:.1f}", f"{r['obs_per_s']:.1f}",
                 f"{r['reingest_night_s']:.2f}", f"{r['size_mb']:.1f}", f"{r['cone_ms']:.1f}",
                 f"{r['lightcurve_ms']:.1f}", *[r["rows"][n] for n in names]]
        print("| " + " | ".join(map(str, cells)) + " |")
    if args.json:
        Path(args.json).write_text(json.dumps(dict(args=vars(args), results=results), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
