"""End to end: simulate, run `python -m sotodlib.site_pipeline.preprocess_tod`, read the archive."""
import subprocess
import sys

import h5py
import numpy as np
import pytest
from astropy.table import Table
from sotodlib import core
from sotodlib.preprocess import preprocess_util as pp_util

from so_transients.campaign.matching import compare_with_truth
from so_transients.site.results import archive_entries, archive_table, observation_table
from so_transients.site.pipeline import failed_groups, run_site_pipeline, write_site_config

from tests.conftest import run_sim

BRIGHT_FLUX = 40000.0    # mJy: far above the glitch step's n_sig = 10 per sample


@pytest.fixture(scope="module")
def flare_run(tmp_path_factory):
    """Five minutes of w16 at f090 with bright flares, a 40 Jy flare and cosmic-ray glitches."""
    root = tmp_path_factory.mktemp("flares")
    sim = run_sim(root, seed=21, observation={"duration": 300.0},
                  instrument={"bands": ["f090"]},
                  flares={"n": 4, "s_peak_mjy": [2000, 5000], "t_rise": [0.5, 10],
                          "list": [{"at_detector": "w16_f090_p215A", "at_time": 150.0,
                                    "t_peak": 150.0, "s_peak_mjy": BRIGHT_FLUX,
                                    "t_rise": 1.0}]},
                  glitches={"enabled": True, "rate_per_hour": 200})
    config = write_site_config(root)
    run_site_pipeline(config)
    return sim, config


def test_no_group_failed(flare_run):
    _, config = flare_run
    assert failed_groups(config) == ""


def test_every_bright_flare_is_found_at_the_right_time_and_place(flare_run):
    sim, config = flare_run
    detections = archive_table(config)
    matched, flares, crossings = compare_with_truth(sim.context.parent, detections)
    crossed = {k[0] for k, v in crossings.items() if len(v)}
    assert crossed == set(flares["source_id"])          # every flare is crossed by the wafer
    found = set(matched["source_id"][matched["source_id"] >= 0])
    assert found == crossed
    hits = matched[matched["source_id"] >= 0]
    assert np.all(hits["dt"] <= 0.5) and np.all(np.degrees(hits["offset"]) * 60 <= 0.5)
    assert np.sum(matched["source_id"] < 0) == 0         # no false detection, glitches included


def test_glitch_step_flags_the_bright_flare_but_does_not_lose_it(flare_run):
    sim, config = flare_run
    ctx = core.Context(str(sim.context))
    aman = ctx.get_obs(sim.obs_ids[0], dets={"wafer_slot": "w16", "bandpass": "f090"})
    _, ctx_pp = pp_util.get_preprocess_context(str(config))
    meta = ctx_pp.get_meta(sim.obs_ids[0], dets={"wafer_slot": "w16", "bandpass": "f090"})
    det = list(aman.det_info.det_id).index("w16_f090_p215A")
    k = np.searchsorted(aman.timestamps, aman.timestamps[0] + 150.0)
    flags = meta.preprocess.glitches.glitch_flags
    assert flags.mask()[det, k - 3:k + 4].any()        # flagged as a glitch ...
    detections = archive_table(config)
    near = np.abs(detections["t_peak"] - aman.timestamps[k]) < 0.5
    assert near.sum() == 1                             # ... and detected once


def test_glitches_make_no_detections(flare_run):
    sim, config = flare_run
    detections = archive_table(config)
    everything = archive_table(config, detected_only=False)
    assert len(sim.glitches) > 5
    rejected_by_time = 0
    for glitch in sim.glitches:
        assert not np.any(np.abs(detections["t_peak"] - glitch["ctime"]) < 0.05)
        near = np.abs(everything["t_peak"] - glitch["ctime"]) < 0.01
        rejected_by_time += np.sum(everything["cut_reason"][near] == "time_order")
    assert rejected_by_time >= 1     # glitch clusters with enough detectors fail the time order


def test_whole_observation_load_matches_per_group_archive(flare_run):
    sim, config = flare_run
    _, ctx = pp_util.get_preprocess_context(str(config))
    whole = observation_table(ctx, sim.obs_ids[0], detected_only=False)
    per_group = archive_table(config, detected_only=False)
    assert len(whole) == len(per_group) > 0
    assert np.allclose(np.sort(whole["t_peak"]), np.sort(per_group["t_peak"]))


def test_catalog_command_writes_ecsv_and_fits_with_units(flare_run, tmp_path):
    _, config = flare_run
    for name in ("det.ecsv", "det.fits"):
        out = tmp_path / name
        subprocess.run([sys.executable, "-m", "so_transients.cli", "catalog", str(config),
                        "-o", str(out)], check=True)
        table = Table.read(out)
        assert len(table) >= 5
        assert str(table["flux"].unit) == "mJy" and str(table["ra"].unit) == "rad"
        assert str(table["t_peak"].unit) == "s"


def test_plots_are_written_for_detections(flare_run):
    sim, config = flare_run
    n = len(archive_table(config))
    pngs = list((sim.context.parent / "preprocess" / "plots").rglob("*_cand*.png"))
    assert len(pngs) == n


def test_noise_only_observation_has_few_false_detections(tmp_path):
    """Stated rate: at most 1 false detection in 5 minutes of one wafer-band (none seen in
    the demo's 20 wafer-band minutes)."""
    run_sim(tmp_path, seed=5, observation={"duration": 300.0}, instrument={"bands": ["f090"]})
    config = write_site_config(tmp_path)
    run_site_pipeline(config)
    assert failed_groups(config) == ""
    assert len(archive_table(config)) <= 1


def test_a_bad_group_fails_alone_and_is_recorded(tmp_path):
    sim = run_sim(tmp_path, seed=6, observation={"duration": 200.0},
                  atmosphere={"enabled": False}, cmb={"enabled": False})
    obs = sim.obs_ids[0]
    with h5py.File(tmp_path / f"tod/{obs}/{obs}_w16_f150.h5", "r+") as f:
        t = f["timestamps"][()]
        t[5000:] += 3.0                                   # a 3 s gap in this detset
        f["timestamps"][...] = t
    config = write_site_config(tmp_path)
    run_site_pipeline(config)
    errors = failed_groups(config)
    assert "f150" in errors and "gaps" in errors and obs in errors
    groups = {(e[1]["wafer_slot"], e[1]["bandpass"])
              for e in archive_entries(tmp_path / "preprocess" / "process_archive.sqlite")}
    assert groups == {("w16", "f090")}
