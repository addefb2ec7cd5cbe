"""Alert records from events tables: what is alerted, followed up and retracted, the
tense, the JSON Schema every record validates against, VOEvent XML and the command."""
import argparse
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import yaml
from astropy.table import Table

from so_transients.alerts.command import get_parser, main, run_alerts, write_alerts
from so_transients.alerts.records import (
    CONTAINMENT_90, CUTOUT_FILES, AlertsConfig, load_schema, plan_alerts, read_alerts, validate
)
from so_transients.alerts.tense import event_tenses
from so_transients.alerts.voevent import NS, to_voevent
from so_transients.common.candidates import typed_table
from so_transients.events import schema

T0 = 1_750_000_000.0
#: The events' UUIDs (their sources': the same with an "f" first).
UUIDS = [f"{k:08x}-0000-5000-8000-000000000000" for k in range(4)]
VALIDATOR = jsonschema.Draft202012Validator(load_schema())


def events_table(**changes):
    """Four events: a new flare (both bands, fitted), a flare of a catalogued source, a
    catalogued source at its flux, and one below the S/N threshold."""
    cols = dict(
        event_id=[0, 1, 2, 3], source_id=[0, 1, 2, 3], event_uuid=UUIDS,
        source_uuid=["f" + u[1:] for u in UUIDS],
        name=["SOTR J000000.0+000000.0", "SOTR J010000.0-100000.0", "SOTR J020000.0-200000.0",
              "SOTR J030000.0-300000.0"],
        ra=[10.0, 15.0, 30.0, 45.0], dec=[-5.0, -10.0, -20.0, -30.0], pos_err=[3.0] * 4,
        t_first=[T0, T0 + 100, T0 + 200, T0 + 300], t_last=[T0 + 60, T0 + 100, T0 + 200, T0 + 300],
        n_detections=[6, 2, 2, 1], obs_ids=["obs_A"] * 4, wafers=["w16,w17", "w16", "w16", "w16"],
        bands=["f090,f150", "f090", "f090", "f150"], peak_flux=[900.0, 800.0, 2000.0, 300.0],
        peak_flux_err=[60.0, 100.0, 100.0, 100.0], peak_band=["f090", "f090", "f090", "f150"],
        joint_snr=[12.0, np.nan, 20.0, np.nan], alpha_mf=[-1.0, np.nan, np.nan, np.nan],
        alpha_mf_err=[0.1, np.nan, np.nan, np.nan], far=[3.6, np.nan, np.nan, np.nan],
        catalogue=["", "socat:", "socat:", ""], cat_source_id=["", "7", "8", ""],
        cat_source_name=["", "QSO A", "Blazar B", ""], cat_separation=[np.nan, 0.2, 0.1, np.nan],
        cat_flux_ratio=[np.nan, 8.0, 1.0, np.nan],
        cat_class=["new", "catalogued_flare", "catalogued", "new"])
    cols.update(changes)
    return typed_table(schema.EVENTS, cols)


def later_table():
    """``events_table`` of a later run: the new flare seen again in obs_B, the flare of QSO A
    now at its catalogue flux."""
    return events_table(obs_ids=["obs_A,obs_B", "obs_A", "obs_A", "obs_A"],
                        t_last=[T0 + 3000, T0 + 100, T0 + 200, T0 + 300],
                        cat_class=["new", "catalogued", "catalogued", "new"],
                        cat_flux_ratio=[np.nan, 1.1, 1.0, np.nan])


def records_of_every_kind(folder):
    """Initial alerts (tense injection) written to ``folder``, then the later run's
    subsequent, updated and retracted ones (tense current): every record. The new flare's
    records name its cutouts, as the alerts command adds them from cutouts.ecsv."""
    events = events_table()
    files = "cutouts/event_0000_f090.fits,cutouts/event_0000_f150.fits"
    events[CUTOUT_FILES] = [files, "", "", ""]
    first = plan(events, tense="injection")
    assert first[0]["cutouts"] == files.split(",") and "cutouts" not in first[1]
    write_alerts(first, folder)
    records = first + plan(later_table(), read_alerts(folder), tense="current")
    assert {r["alert_type"] for r in records} >= {"initial", "subsequent", "retraction"}
    return records


def fits_table():
    return Table(dict(event_id=[0], bandpass=["f090"], t_rise=[10.0], t_rise_err=[3.0],
                      t_decay=[20.0], t_decay_err=[4.0], fit_ok=[True]))


def plan(events, history=None, covered=("obs_A",), tense="test", cfg=None):
    return plan_alerts(events, fits_table(), [tense] * len(events), history or {}, covered,
                       cfg or AlertsConfig())


def test_initial_alerts_of_the_transients_above_threshold():
    records = plan(events_table())
    assert [r["so_event_id"] for r in records] == UUIDS[:2]   # catalogued and faint: none
    assert [r["so_source_id"] for r in records] == ["f" + u[1:] for u in UUIDS[:2]]
    new, flare = records
    for r in records:
        VALIDATOR.validate(r)
        assert r["alert_type"] == "initial" and r["record_number"] == 1
        assert r["alert_tense"] == "test"
    assert new["flux_density"] == pytest.approx(900.0e-26) and new["flux_density_mjy"] == 900.0
    assert new["flux_density_error"] == pytest.approx(60.0e-26)
    assert new["flux_density_spectral_point"] == 93_000.0
    assert new["spectral_band"][0] < 93_000.0 < new["spectral_band"][1]
    assert new["ra_dec_error"] == pytest.approx(CONTAINMENT_90 * 3.0 / 3600.0)
    assert CONTAINMENT_90 == pytest.approx(2.1460, abs=1e-4)   # 90 % of a 2-D Gaussian
    # far 3.6 per wafer-band-hour: 1e-3 Hz per wafer-band, 36 times that for the LAT
    assert new["far_per_wafer_band"] == pytest.approx(1e-3) and new["far_wafer_bands"] == 36
    assert new["far"] == pytest.approx(36e-3) and new["snr"] == 12.0
    assert new["spectral_index"] == -1.0 and new["spectral_index_bands"] == "f090/f150"
    assert new["duration"] == 30.0 and new["duration_error"] == pytest.approx(5.0)
    assert new["trigger_time"].endswith("Z") and new["detection_span"] == 60.0
    assert new["obs_ids"] == ["obs_A"] and new["wafers"] == ["w16", "w17"]
    assert flare["snr"] == 8.0 and "far" not in flare and "spectral_index" not in flare
    assert flare["crossmatch_class"] == "catalogued_flare" and flare["known_source"] == "QSO A"
    assert flare["flux_ratio"] == 8.0


def test_followups_and_retractions(tmp_path):
    write_alerts(plan(events_table()), tmp_path)
    history = read_alerts(tmp_path)
    assert len(history) == 2
    # the same events again: nothing new
    assert plan(events_table(), history) == []
    # the new flare seen again in obs_B; the flare of QSO A now at its catalogue flux
    later = later_table()
    records = {r["so_event_id"] if "so_event_id" in r else r["id"]: r for r in plan(later, history)}
    seen = records[UUIDS[0]]
    assert seen["alert_type"] == "subsequent" and seen["record_number"] == 2
    assert seen["update_message"] == "seen again in obs_B"
    assert seen["id"] == history[seen["id"]][0]["id"]
    retracted = [r for r in records.values() if r["alert_type"] == "retraction"]
    assert len(retracted) == 1 and "QSO A" in retracted[0]["update_message"]
    assert "catalogued source at its catalogue flux" in retracted[0]["update_message"]
    for r in records.values():
        VALIDATOR.validate(r)
    # a new flare of the same source 3 h later, in another run (its own source UUID): the
    # alert of that source goes on, with the first alert's source id
    again = events_table(obs_ids=["obs_C"] + ["obs_A"] * 3, t_first=[T0 + 3 * 3600.0] + [
        T0 + 100, T0 + 200, T0 + 300], t_last=[T0 + 3 * 3600.0 + 30] + [T0 + 100, T0 + 200,
                                                                         T0 + 300],
        source_uuid=["e" + UUIDS[0][1:]] + ["f" + u[1:] for u in UUIDS[1:]],
        event_uuid=["d" + UUIDS[0][1:]] + UUIDS[1:])
    (flare,) = plan(again, history)
    first = history[flare["id"]][0]
    assert flare["alert_type"] == "subsequent" and flare["record_number"] == 2
    assert flare["so_source_id"] == first["so_source_id"] != str(again["source_uuid"][0])
    assert flare["so_event_id"] == str(again["event_uuid"][0])
    assert flare["update_message"] == ("a new flare of the same source, 3.0 h after its last "
                                       "alerted detection, in obs_C")
    VALIDATOR.validate(flare)
    # a re-analysis of the same observation changing the flux: an update
    changed = events_table(peak_flux=[950.0, 800.0, 2000.0, 300.0])
    (update,) = plan(changed, history)
    assert update["alert_type"] == "update" and "flux_density" in update["update_message"]


def test_an_event_gone_is_retracted_only_when_its_observations_were_reanalysed(tmp_path):
    write_alerts(plan(events_table()), tmp_path)
    history = read_alerts(tmp_path)
    others = events_table()[2:]                       # the two alerted events are gone
    assert plan(others, history, covered=["obs_C"]) == []
    retractions = plan(others, history, covered=["obs_A"])
    assert [r["alert_type"] for r in retractions] == ["retraction"] * 2
    assert all("re-analysis of its observations (obs_A)" in r["update_message"]
               for r in retractions)
    write_alerts(retractions, tmp_path)
    assert plan(others, read_alerts(tmp_path), covered=["obs_A"]) == []   # retracted once


def test_far_and_snr_thresholds():
    assert [r["so_event_id"] for r in plan(events_table(), cfg=AlertsConfig(min_snr=10))] == UUIDS[:1]
    # event 0: 1e-3 Hz per wafer-band, 0.036 Hz for the LAT's 36; event 1 none
    assert plan(events_table(), cfg=AlertsConfig(max_far_hz=1e-2)) == []
    assert len(plan(events_table(), cfg=AlertsConfig(max_far_hz=0.04))) == 1
    one = AlertsConfig(max_far_hz=1e-2, wafer_bands=1)   # one wafer-band searched
    (record,) = plan(events_table(), cfg=one)
    assert record["far"] == pytest.approx(1e-3) and record["far_wafer_bands"] == 1


def test_schema_refuses_broken_records():
    good = plan(events_table())[0]
    for broken in ({**good, "alert_tense": "archival"}, {**good, "flux_density": "900 mJy"},
                   {k: v for k, v in good.items() if k != "ra"},
                   {**good, "alert_type": "update"},          # an update names what it follows
                   {**good, "dec": -91.0}, {**good, "extra": 1},
                   {**good, "trigger_time": "2025-06-15 12:00:00"}):
        with pytest.raises(ValueError, match="does not follow alert.schema.json"):
            validate(broken)


def test_voevent_packet():
    record = plan(events_table(), tense="injection")[0]
    root = ET.fromstring(to_voevent(record))
    assert root.tag == f"{{{NS}}}VOEvent" and root.get("version") == "2.0"
    assert root.get("role") == "test"
    assert root.get("ivorn").endswith(f"#{record['id']}-01")
    params = {p.get("name"): p for p in root.iter("Param")}
    assert params["flux_density_mjy"].get("unit") == "mJy"
    assert float(params["flux_density_mjy"].get("value")) == 900.0
    pos = root.find("WhereWhen/ObsDataLocation/ObservationLocation/AstroCoords/Position2D")
    assert float(pos.find("Value2/C1").text) == 10.0
    assert float(pos.find("Error2Radius").text) == pytest.approx(record["ra_dec_error"])
    assert ET.fromstring(to_voevent({**record, "alert_tense": "current"})).get("role") == \
        "observation"


def test_every_packet_is_valid_against_the_ivoas_voevent_schema(tmp_path):
    """New, subsequent, updated and retracted alerts, as VOEvent 2.0 XML, against the IVOA's
    own XSD (tests/alerts/schemas/VOEvent-v2.0.xsd), not only against what we expect."""
    xmlschema = pytest.importorskip("xmlschema")
    xsd = xmlschema.XMLSchema(str(Path(__file__).parent / "schemas" / "VOEvent-v2.0.xsd"))
    for record in records_of_every_kind(tmp_path):
        errors = [str(e.reason) for e in xsd.iter_errors(to_voevent(record))]
        assert not errors, (record["alert_type"], errors)


#: The core blocks a mission schema of GCN composes (gcn/notices/<mission>/*.schema.json)
GCN_CORE = ("Alert", "Reporter", "Event", "DateTime", "Localization", "Statistics", "Duration",
            "Spectral")


def gcn_validator():
    """A validator of the GCN core blocks, composed as a mission schema composes them (``allOf``
    of their ``$ref``s), from nasa-gcn/gcn-schema's own files (tests/alerts/schemas/gcn)."""
    from referencing import Registry, Resource

    root = Path(__file__).parent / "schemas" / "gcn" / "notices" / "core"
    resources = []
    for path in sorted(root.rglob("*.schema.json")):
        schema = json.loads(path.read_text())
        resources.append((schema["$id"], Resource.from_contents(schema)))
    base = "https://gcn.nasa.gov/schema/main/gcn/notices/so/alert.schema.json"
    mission = {"$id": base, "$schema": "https://json-schema.org/draft/2020-12/schema",
               "type": "object",
               "allOf": [{"$ref": f"../core/{name}.schema.json"} for name in GCN_CORE]}
    return jsonschema.Draft202012Validator(mission, registry=Registry().with_resources(resources))


def test_every_record_is_valid_against_gcns_own_core_schemas(tmp_path):
    """New, subsequent, updated and retracted alerts against GCN's core blocks as a mission
    schema composes them: a field the core defines has the core's type and meaning."""
    validator = gcn_validator()
    for record in records_of_every_kind(tmp_path):
        errors = [f"{'/'.join(map(str, e.path))}: {e.message}" for e in
                  validator.iter_errors(record)]
        assert not errors, (record["alert_type"], errors)


def _site_config(tmp_path, simulated):
    """A dataset folder (with the simulator's marker and truth when ``simulated``) and a
    preprocess config naming its context."""
    dataset = tmp_path / "dataset"
    (dataset / "truth").mkdir(parents=True)
    (dataset / "context.yaml").write_text("tags: {}\n")
    if simulated:
        (dataset / "sim_config.yaml").write_text("seed: 1\n")
        Table(dict(source_id=[0, 0], band=["f090", "f150"], ra=np.radians([10.0, 10.0]),
                   dec=np.radians([-5.0, -5.0]), t_peak=[T0 + 30] * 2, s_peak=[900.0] * 2,
                   t_rise=[30.0] * 2, t_decay=[30.0] * 2, eta_rise=[1.0] * 2,
                   eta_decay=[1.0] * 2)).write(dataset / "truth" / "flares.ecsv")
    config = tmp_path / "preprocess.yaml"
    config.write_text(yaml.safe_dump({"context_file": str(dataset / "context.yaml"),
                                      "archive": {"index": "x.sqlite"}}))
    return dataset, config


def test_tense_from_the_dataset(tmp_path):
    sim, _ = _site_config(tmp_path / "sim", simulated=True)
    real, _ = _site_config(tmp_path / "real", simulated=False)
    assert list(event_tenses(events_table(), sim, AlertsConfig())) == \
        ["injection", "test", "test", "test"]
    assert set(event_tenses(events_table(), real, AlertsConfig())) == {"current"}


def test_command_writes_valid_alerts(tmp_path):
    _, config = _site_config(tmp_path, simulated=True)
    folder = tmp_path / "events"
    folder.mkdir()
    events = events_table()
    events.meta["provenance"] = {"preprocess_config": str(config), "obs_ids": ["obs_A"]}
    events.write(folder / "events.ecsv")
    out = tmp_path / "alerts"
    args = get_parser(argparse.ArgumentParser()).parse_args([str(folder), "-o", str(out),
                                                             "--voevent"])
    assert main(args) == 0
    files = sorted(out.glob("*.json"))
    assert len(files) == 2 and len(list(out.glob("*.xml"))) == 2
    records = [json.loads(p.read_text()) for p in files]
    for r in records:
        VALIDATOR.validate(r)
    assert sorted(r["alert_tense"] for r in records) == ["injection", "test"]
    assert main(args) == 0 and len(list(out.glob("*.json"))) == 2      # nothing new
    (folder / "events.ecsv").unlink()
    with pytest.raises(ValueError, match="no events.ecsv"):
        run_alerts(folder, out, AlertsConfig())


def test_an_events_table_without_uuids_is_refused_by_name(tmp_path):
    """An events table of an older version (run-local ids only) is refused, naming the file
    and what to do, rather than failing on a missing column."""
    folder = tmp_path / "events"
    folder.mkdir()
    old = events_table()
    old.remove_columns(["event_uuid", "source_uuid"])
    old.write(folder / "events.ecsv")
    with pytest.raises(ValueError, match=r"events\.ecsv: no event_uuid, source_uuid .*again"):
        run_alerts(folder, tmp_path / "alerts", AlertsConfig(), tense="test")


def test_the_default_trials_factor_is_the_lats_wafer_bands():
    from so_transients.sim.focal_plane import lat_layout

    assert AlertsConfig().wafer_bands == sum(len(w) * len(b) for _, _, w, b in lat_layout())
