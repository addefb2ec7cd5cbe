"""``so-transients events`` end to end: simulate, run the site pipeline, build the events
from the real archive, and with a group's data gone."""
import numpy as np
import pytest
from astropy.table import Table
from scipy.stats import norm

from so_transients.common.angles import ARCMIN
from so_transients.common.angles import sky_separation
from so_transients.cli import main as cli_main
from so_transients.site.pipeline import PRODUCTION, run_site_pipeline, write_site_config
from so_transients.sources.catalog import read_catalogue

from tests.conftest import add_socat_asteroid, run_sim

pytestmark = pytest.mark.slow   # end to end: simulates and runs the pipeline

SLOW = dict(at_detector="w16_f090_p100A", at_time=80.0, t_peak=80.0, s_peak_mjy=3000.0,
            t_rise=30.0, spectral_index=-1.0)
FAST = dict(at_detector="w16_f090_p250A", at_time=150.0, t_peak=150.0, s_peak_mjy=3000.0,
            t_rise=1.0)
#: Largest fraction of a 3 Jy source a pca_filter takes before the matched filter: a measured
#: figure, not derived (docs/results/events.md, "Known limits": 2-10 % at the bright
#: crossings of this test with the paper config, whose PCA sees the crossings; the production
#: config used here hides them from it, transient_pca_mask). The campaign injects after the
#: filter and does not see it.
PCA_LOSS = 0.10
#: The bright light-curve points of both bands (8 here) each within K_POINTS of their own
#: errors: a 1 % chance of one false failure among 8 Gaussian points (Bonferroni).
K_POINTS = float(norm.isf(0.01 / (2 * 8)))


@pytest.fixture(scope="module")
def events_run(module_tmp):
    """Four minutes of w16 in both bands, 12 s sweeps (a crossing every 12 s), atmosphere
    and white noise, a slow flare with spectral index -1 and a fast flat one; the production
    site config (the default; its false-alarm rate is calibrated: the paper config's fixed
    cut let a noise fluctuation through here, at fitted S/N 5.02, once the second pass
    normalized bright detectors' S/N by measurement), then ``so-transients events`` on it.
    (Without the atmosphere the paper config's pca_filter takes the bright flare itself as a
    mode: f090 loses a quarter of its flux.)"""
    root = module_tmp("events")
    sim = run_sim(root, seed=31, observation={"duration": 240.0},
                  scan={"sweep_time": 12.0},
                  cmb={"enabled": False}, flares={"list": [SLOW, FAST]})
    config = write_site_config(root, template=PRODUCTION)
    run_site_pipeline(config)
    out = root / "events"
    assert cli_main(["events", str(config), "-o", str(out), "--nproc", "2", "-q"]) == 0
    return sim, root, config, out


def read(out, name):
    return Table.read(out / f"{name}.ecsv")


def truth_of(root):
    flares = Table.read(root / "truth" / "flares.ecsv")
    return {int(i): flares[flares["source_id"] == i] for i in np.unique(flares["source_id"])}


def event_of(events, flare):
    sep = sky_separation(np.radians(events["ra"]), np.radians(events["dec"]),
                         flare["ra"][0], flare["dec"][0])
    return events[sep < 0.5 * ARCMIN]


def test_each_flare_is_one_event_at_its_position(events_run):
    _, root, _, out = events_run
    events = read(out, "events")
    assert len(events) == 2
    for flare in truth_of(root).values():
        mine = event_of(events, flare)
        assert len(mine) == 1
        assert mine["bands"][0] == "f090,f150"


def test_light_curve_of_the_slow_flare(events_run):
    _, root, _, out = events_run
    events, lc = read(out, "events"), read(out, "lightcurves")
    slow = truth_of(root)[0]
    eid = event_of(events, slow)["event_id"][0]
    mine = lc[lc["event_id"] == eid]
    for band in ("f090", "f150"):
        points = mine[mine["bandpass"] == band]
        assert len(points) >= 8                 # 60 s of flare plus a minute either side
        assert np.isfinite(points["upper_limit"]).any() and points["detected"].any()
        truth = slow[slow["band"] == band][0]
        expected = truth["s_peak"] * np.clip(1 - np.abs(points["ctime"] - truth["t_peak"])
                                             / truth["t_rise"], 0, None)
        off = expected == 0
        assert off.sum() >= 4
        # where the flare is off, the forced fluxes are noise: every one within 5 sigma
        assert np.all(np.abs(points["flux"][off] / points["flux_err"][off]) < 5)
        # where it is bright, the flux follows the light curve, less what the shipped
        # pca_filter takes of a 3 Jy source before the matched filter: flux = (1 - L) x
        # expected + noise, with L between 0 and PCA_LOSS (a measured figure, see its
        # definition). Each point within K_POINTS of its own errors of that band.
        bright = expected > 500
        assert bright.sum() >= 3
        ratio = np.asarray(points["flux"][bright] / expected[bright])
        sigma = np.asarray(points["flux_err"][bright] / expected[bright])
        assert np.all(ratio > 1 - PCA_LOSS - K_POINTS * sigma), (ratio, sigma)
        assert np.all(ratio < 1 + K_POINTS * sigma), (ratio, sigma)
    assert set(mine["frequency"]) == {90, 150}
    assert lc["flux"].unit == "mJy" and lc["ra"].unit == "deg"


def test_spectral_index_and_light_curve_fit_of_the_slow_flare(events_run):
    _, root, _, out = events_run
    events, fits = read(out, "events"), read(out, "lightcurve_fits")
    slow = truth_of(root)[0]
    # the simulator scales s_peak (given at 93 GHz) to each band's centre frequency
    assert slow[slow["band"] == "f150"]["s_peak"][0] == pytest.approx(3000.0 * (145 / 93) ** -1)
    event = event_of(events, slow)[0]
    # within 3 sigma of the injected -1 (its error comes from the crossings' flux errors)
    assert abs(event["alpha_mf"] + 1.0) < 3 * event["alpha_mf_err"]
    assert event["alpha_mf_err"] < 0.2
    for band in ("f090", "f150"):
        fit = fits[(fits["event_id"] == event["event_id"]) & (fits["bandpass"] == band)][0]
        truth = slow[slow["band"] == band][0]
        assert fit["fit_ok"]
        for name in ("s_peak", "t_peak"):
            assert abs(fit[name] - truth[name]) < 4 * fit[f"{name}_err"], (band, name)
        # crossings 12 s apart leave rise and decay times trading against each other and
        # the peak time; their sum, the flare's duration, is well measured (20 %)
        duration = fit["t_rise"] + fit["t_decay"]
        assert abs(duration - 2 * truth["t_rise"]) < 0.2 * 2 * truth["t_rise"]
    assert not event["single_band"] and event["joint_snr"] > 10


def test_tables_and_figures_are_written_with_provenance(events_run):
    _, _, config, out = events_run
    for name in ("events", "lightcurves"):
        fits = Table.read(out / f"{name}.fits")
        assert len(fits) == len(read(out, name))
    assert read(out, "events").meta["provenance"]["preprocess_config"] == str(config.resolve())
    assert len(list((out / "figures").glob("event_*.png"))) == 2
    assert len(read(out, "failures")) == 0


def test_a_missing_group_is_recorded_and_the_other_band_still_measured(events_run, tmp_path,
                                                                      capsys):
    sim, root, config, _ = events_run
    obs = sim.obs_ids[0]
    (root / f"tod/{obs}/{obs}_w16_f150.h5").rename(tmp_path / "moved.h5")
    try:
        out = tmp_path / "events"
        assert cli_main(["events", str(config), "-o", str(out), "-q"]) == 1
        assert "FAILED" in capsys.readouterr().err
        assert cli_main(["events", str(config), "-o", str(out), "-q", "--partial"]) == 0
    finally:
        (tmp_path / "moved.h5").rename(root / f"tod/{obs}/{obs}_w16_f150.h5")
    failures = read(out, "failures")
    assert list(failures["group"]) == ["w16/f150"] and failures["obs_id"][0] == obs
    events, lc = read(out, "events"), read(out, "lightcurves")
    assert len(events) == 2
    assert set(lc["bandpass"]) == {"f090"}
    assert all("f150 not measured" in note for note in events["note"])


def test_groups_the_site_pipeline_failed_fail_the_events(events_run, tmp_path, capsys):
    """Every group failed in the site pipeline (its TOD files gone): `events` says which and
    exits 1, not 0 with zero events and a warning; --partial accepts it."""
    sim, root, _, _ = events_run
    obs = sim.obs_ids[0]
    files = sorted((root / "tod" / obs).glob("*.h5"))
    config = write_site_config(root, path=tmp_path / "preprocess.yaml", template=PRODUCTION,
                               results=tmp_path / "results")
    for f in files:
        f.rename(tmp_path / f.name)
    try:
        run_site_pipeline(config)
    finally:
        for f in files:
            (tmp_path / f.name).rename(f)
    out = tmp_path / "events"
    assert cli_main(["events", str(config), "-o", str(out), "-q"]) == 1
    err = capsys.readouterr().err
    assert f"FAILED {obs} w16/f090: site pipeline" in err and "w16/f150" in err
    assert sorted(read(out, "failures")["group"]) == ["w16/f090", "w16/f150"]
    assert cli_main(["events", str(config), "-o", str(out), "-q", "--partial"]) == 0


def test_events_cross_matched_with_a_socat_catalogue(events_run, tmp_path):
    """The slow flare's position catalogued in socat at 100 mJy makes its event a flare of
    that source (3 Jy measured: above 5x); an asteroid whose ephemeris passes the fast flare at
    its time makes that event a solar-system object. The forced photometry is reused."""
    import shutil

    import astropy.units as u
    import yaml
    from astropy.coordinates import ICRS
    from socat.client.db import Client

    _, root, config, out = events_run
    slow, fast = truth_of(root)[0][0], truth_of(root)[1][0]
    db = tmp_path / "socat.db"
    client = Client(db_url=f"sqlite:///{db}")
    client.create_source(position=ICRS(ra=slow["ra"] * u.rad, dec=slow["dec"] * u.rad),
                         name="Catalogued star", flux=100 * u.mJy)
    add_socat_asteroid(client, "Vesta", 4, [
        (int(round(fast["t_peak"])) + dt,
         ICRS(ra=fast["ra"] * u.rad, dec=(fast["dec"] + dt / 3600 * 0.2 * np.pi / 180) * u.rad))
        for dt in (-3600, 3600)])
    copy = tmp_path / "events"
    shutil.copytree(out, copy)
    events_yaml = tmp_path / "events.yaml"
    events_yaml.write_text(yaml.safe_dump({"preprocess": str(config), "output": str(copy),
                                           "catalogue": f"socat://{db}"}))
    assert cli_main(["events", str(events_yaml), "-q"]) == 0
    events = read(copy, "events")
    flare, moving = event_of(events, truth_of(root)[0])[0], event_of(events, truth_of(root)[1])[0]
    assert flare["cat_class"] == "catalogued_flare"
    assert flare["cat_source_name"] == "Catalogued star"
    (star_id,) = read_catalogue(f"socat://{db}").source_id   # socat's id, as a string
    assert flare["cat_source_id"] == star_id
    assert flare["cat_separation"] < 0.5 and flare["catalogue"] == f"socat://{db}"
    assert flare["cat_flux_ratio"] == pytest.approx(flare["peak_flux"] / 100.0)
    assert moving["cat_class"] == "solar_system" and moving["cat_source_name"] == "Vesta"
    assert events["cat_separation"].unit == "arcmin"
    # without a catalogue the columns say that none was searched
    assert list(np.ma.filled(read(out, "events")["cat_class"], "")) == ["", ""]


def test_alerts_of_the_injected_flares(events_run, tmp_path):
    """`so-transients alerts` on the simulated events: one initial alert per flare, tense
    `injection` (the dataset is a simulation and both events match an injected flare), each
    valid against the alert schema; a second run adds nothing."""
    import argparse
    import json

    import jsonschema

    from so_transients.alerts.command import get_parser, main
    from so_transients.alerts.records import load_schema

    _, root, _, out = events_run
    args = get_parser(argparse.ArgumentParser()).parse_args(
        [str(out), "-o", str(tmp_path / "alerts"), "--voevent"])
    assert main(args) == 0
    records = [json.loads(p.read_text()) for p in sorted((tmp_path / "alerts").glob("*.json"))]
    assert len(records) == 2 and len(list((tmp_path / "alerts").glob("*.xml"))) == 2
    for record in records:
        jsonschema.Draft202012Validator(load_schema()).validate(record)
        assert record["alert_tense"] == "injection" and record["alert_type"] == "initial"
        assert record["crossmatch_class"] == "" and record["bands"] == ["f090", "f150"]
    assert main(args) == 0 and len(list((tmp_path / "alerts").glob("*.json"))) == 2
