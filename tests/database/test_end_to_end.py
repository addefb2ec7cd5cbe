"""The events database on a real run: simulate an observation with a flare, run the site
pipeline, ``so-transients catalog`` and ``so-transients events``, then ingest the output on
SQLite and PostgreSQL."""
import json
import shutil
import uuid

import numpy as np
import pytest
import sqlalchemy as sa
from astropy.io import fits
from astropy.table import Table

from so_transients.alerts.command import run_alerts
from so_transients.alerts.records import AlertsConfig
from so_transients.cli import main as cli_main
from so_transients.database import schema
from so_transients.database.command import get_parser, main
from so_transients.database.engine import open_database
from so_transients.database.queries import counts, find_events, find_sources, lightcurve
from so_transients.site.pipeline import PAPER, run_site_pipeline, write_site_config
from so_transients.common.times import utc

from tests.conftest import run_sim

pytestmark = pytest.mark.slow   # end to end: simulates and runs the pipeline

FLARE = dict(at_detector="w16_f090_p250A", at_time=60.0, t_peak=60.0, s_peak_mjy=3000.0,
             t_rise=3.0)
#: Columns of ctime seconds in each file, and the ISO UTC columns made from them.
TIMES = {"events.ecsv": {"t_first": "t_first_utc", "t_last": "t_last_utc"},
         "lightcurves.ecsv": {"ctime": "time"},
         "lightcurve_fits.ecsv": {"t_peak": None},
         "detections.ecsv": {"t_median": None, "t_start": None, "t_stop": None,
                             "t_peak": "t_peak_utc"}}


def db(*argv) -> int:
    return main(get_parser().parse_args([str(a) for a in argv]))


@pytest.fixture(scope="module")
def real_run(module_tmp):
    """Two minutes of w16 in both bands with one bright flare, through the whole chain; the
    events folder next to the catalogue, as ``make demo`` leaves them."""
    root = module_tmp("db_chain")
    run_sim(root, seed=5, observation={"duration": 120.0}, scan={"sweep_time": 12.0},
            cmb={"enabled": False}, flares={"list": [FLARE]})
    config = write_site_config(root, template=PAPER)
    run_site_pipeline(config)
    assert cli_main(["catalog", str(config), "-o", str(root / "detections.ecsv"),
                     "--overwrite"]) == 0
    assert cli_main(["events", str(config), "-o", str(root / "events"), "-q"]) == 0
    return root


def as_another_observation(root, dest, dt, suffix):
    """The run's files as if of another observation ``dt`` seconds later (obs_id with
    ``suffix``), with the detections next to them."""
    dest.mkdir()
    for name, columns in TIMES.items():
        table = Table.read((root if name == "detections.ecsv" else root / "events") / name)
        for col in ("obs_id", "obs_ids"):
            if col in table.colnames:
                table[col] = [f"{v}{suffix}" for v in table[col]]
        for col in ("event_uuid", "source_uuid"):      # another observation: other events
            if col in table.colnames:
                table[col] = [str(uuid.uuid5(uuid.UUID(v), suffix)) for v in table[col]]
        for ctime, iso in columns.items():
            table[ctime] += dt
            if iso:
                table[iso] = utc(table[ctime])
        prov = table.meta.get("provenance")
        if prov:
            prov["obs_ids"] = [f"{v}{suffix}" for v in prov["obs_ids"]]
        table.write(dest / name)
    return dest


def test_a_real_run_ingested_twice_then_seen_again(real_run, new_db, tmp_path):
    url = new_db()
    events = Table.read(real_run / "events" / "events.ecsv")
    points = Table.read(real_run / "events" / "lightcurves.ecsv")
    assert len(events) >= 1
    assert db("ingest", "--db", url, real_run / "events") == 0
    first = counts(open_database(url, create=False))
    assert first["events"] == len(events) and first["lightcurve_points"] == len(points)
    assert first["detections"] == np.sum(events["n_detections"])
    assert first["observations"] == 1
    # each event's cutout per band, its pixels in Jy as lightcurvedb's Cutout holds them
    cutouts = Table.read(real_run / "events" / "cutouts.ecsv")
    assert first["cutouts"] == len(cutouts) >= len(events)
    engine = open_database(url, create=False)
    with engine.connect() as conn:
        stored = conn.execute(sa.select(schema.CUTOUTS.c.run_event_id, schema.CUTOUTS.c.data,
                                        schema.CUTOUTS.c.wcs, schema.CUTOUTS.c.peak_ra)
                              .order_by(schema.CUTOUTS.c.id)).all()
    image = fits.getdata(real_run / "events" / cutouts["file"][0])
    data = np.array(stored[0].data, dtype=float)          # null (nothing fell there): NaN
    assert data.shape == image.shape
    assert np.allclose(data, image / 1000.0, equal_nan=True, rtol=1e-6)
    assert "RA---TAN" in stored[0].wcs and stored[0].peak_ra == pytest.approx(
        cutouts["peak_ra"][0])
    assert db("ingest", "--db", url, real_run / "events") == 0
    assert counts(open_database(url, create=False)) == first
    # the same flare seen in another observation 12 hours later keeps its source id
    later = as_another_observation(real_run, tmp_path / "later", 12 * 3600.0, "_later")
    before = find_sources(open_database(url, create=False))
    assert db("ingest", "--db", url, later) == 0
    engine = open_database(url, create=False)
    after = find_sources(engine)
    assert list(after["id"]) == list(before["id"])
    assert list(after["n_events"]) == list(2 * before["n_events"])
    stored = find_events(engine)
    assert len(stored) == 2 * len(events)
    source = after["id"][np.argmax(after["n_events"])]
    obs = {str(o) for o in lightcurve(engine, source)["obs_id"]}
    assert len(obs) == 2 and any(o.endswith("_later") for o in obs)


def test_a_run_ingested_from_its_archive(real_run, new_db, tmp_path):
    """Without a catalogue next to the events folder the detections come from the archive
    named in the events' provenance."""
    alone = shutil.copytree(real_run / "events", tmp_path / "events_only")
    url = new_db()
    assert db("ingest", "--db", url, alone) == 0
    events = Table.read(alone / "events.ecsv")
    assert counts(open_database(url, create=False))["detections"] == np.sum(events["n_detections"])


def test_alert_ids_name_the_database_rows_and_survive_a_reingest(real_run, new_db, tmp_path):
    """An alert's so_event_id finds its event in the database and its so_source_id the
    source whose light curve holds it; ingesting the run again keeps every id (row ids and
    UUIDs) on both back ends."""
    url = new_db()
    alerts = run_alerts(real_run / "events", tmp_path / "alerts", AlertsConfig())
    assert alerts, "the bright flare is alerted"
    assert db("ingest", "--db", url, real_run / "events") == 0

    def ids():
        engine = open_database(url, create=False)
        found = {}
        for alert in alerts:
            (event,) = find_events(engine, event=alert["so_event_id"])
            curve = lightcurve(engine, alert["so_source_id"])
            assert curve.meta["source"]["id"] == event["source_id"]
            assert curve.meta["source"]["uuid"] == alert["so_source_id"]
            assert event["run_event_id"] in set(curve["run_event_id"])
            found[alert["id"]] = (int(event["id"]), int(event["source_id"]))
        return found, sorted(find_events(engine)["id"]), sorted(find_sources(engine)["uuid"])

    first = ids()
    assert db("ingest", "--db", url, real_run / "events") == 0
    assert ids() == first


def test_a_sources_records_as_lightcurvedb_ingests_them(real_run, new_db, tmp_path):
    """``db lightcurve --lightcurvedb`` of the flare's source: one Source, an Instrument per
    band and tube, its FluxMeasurements in Jy, and a Cutout per event and band tied to the
    measurement of its crossing. Where lightcurvedb's current models and storage are
    installed (its main branch; the package index's 0.0.2 predates them) they take the records:
    validated by its pydantic models, written to its parquet backend and read back as the
    source's light curve."""
    url = new_db()
    assert db("ingest", "--db", url, real_run / "events") == 0
    engine = open_database(url, create=False)
    source = find_sources(engine)[0]
    out = tmp_path / "records.json"
    assert db("lightcurve", "--db", url, source["uuid"], "--lightcurvedb", "-o", out) == 0
    records = json.loads(out.read_text())
    measured = {m["measurement_id"]: m for m in records["flux_measurements"]}
    cutouts = Table.read(real_run / "events" / "cutouts.ecsv")
    assert len(records["cutouts"]) == len(cutouts) >= 1
    for cutout in records["cutouts"]:
        m = measured[cutout["measurement_id"]]          # the measurement of its crossing
        assert (cutout["frequency"], cutout["module"], cutout["time"]) == (
            m["frequency"], m["module"], m["time"])
        assert cutout["units"] == "Jy" and np.nanmax(cutout["data"]) > 0.5   # a 3 Jy flare
    pytest.importorskip("lightcurvedb.storage.parquet.backend",
                        reason="lightcurvedb's current storage (its main branch) not installed")
    import asyncio

    from lightcurvedb.models import Cutout, FluxMeasurement, Instrument, Source
    from lightcurvedb.storage.parquet.backend import generate_pandas_backend

    async def ingest():
        backend = await generate_pandas_backend(tmp_path / "lightcurvedb")
        await backend.instruments.create_batch([Instrument(**i) for i in records["instruments"]])
        await backend.sources.create_batch([Source(**s) for s in records["sources"]])
        await backend.fluxes.create_batch([FluxMeasurement(**m)
                                           for m in records["flux_measurements"]])
        await backend.cutouts.create_batch([Cutout(**c) for c in records["cutouts"]])
        source_id = uuid.UUID(records["sources"][0]["source_id"])
        first = records["instruments"][0]
        curve = await backend.lightcurves.get_instrument_lightcurve(
            source_id, first["module"], first["frequency"])
        return (await backend.lightcurves.get_frequencies_for_source(source_id),
                [float(f) for f in curve.flux], first)

    frequencies, fluxes, first = asyncio.run(ingest())
    assert sorted(frequencies) == sorted({m["frequency"] for m in measured.values()})
    assert sorted(fluxes) == pytest.approx(sorted(
        m["flux"] for m in measured.values()
        if (m["frequency"], m["module"]) == (first["frequency"], first["module"])))
