"""Bad input gets a clear answer and loses nothing (in-process sotodlib Pipeline runs)."""
import numpy as np
import pytest
from sotodlib import core
from sotodlib.preprocess import Pipeline

from so_transients.site.results import FIRST, amplitude, proc_table

from tests.conftest import load_group, run_sim, run_steps

STEPS = [{"name": "transient_filter", "process": {}, "calc": True, "save": True},
         {"name": "transient_find", "calc": {}, "save": True},
         {"name": "transient_cuts", "calc": {}, "save": True},
         {"name": "transient_fit", "calc": {}, "save": True}]
FLARE_TIME = 40.0


@pytest.fixture(scope="module")
def dataset(module_tmp):
    return run_sim(module_tmp("bad"), seed=9, observation={"duration": 130.0},
                   instrument={"bands": ["f090"]}, atmosphere={"enabled": False},
                   cmb={"enabled": False},
                   flares={"list": [{"at_detector": "w16_f090_p215A", "at_time": FLARE_TIME,
                                     "t_peak": FLARE_TIME, "s_peak_mjy": 3000.0,
                                     "t_rise": 2.0}]})


load = load_group


def run(aman):
    return run_steps(aman, STEPS)


def found_flare(aman, proc, dataset):
    table = proc_table(proc, aman.obs_info.obs_id)
    t = table[np.asarray(table["detected"], bool)]["t_peak"]
    return np.any(np.abs(t - dataset.flares["t_peak"][0]) < 0.5)


def test_clean_data_finds_the_flare(dataset):
    aman = load(dataset)
    assert found_flare(aman, run(aman), dataset)


def test_nan_and_inf_samples_are_ignored(dataset):
    aman = load(dataset)
    aman.signal[0, 1000:1010] = np.nan
    aman.signal[1, 2000] = np.inf
    proc = run(aman)
    assert np.all(np.isfinite(aman.transient_snr))
    assert np.all(np.isfinite(amplitude(aman)))
    assert np.all(aman.transient_snr[0, 1000:1010] == 0) and aman.transient_snr[1, 2000] == 0
    assert found_flare(aman, proc, dataset)


def test_dead_detectors_are_marked_and_the_rest_still_works(dataset):
    aman = load(dataset)
    aman.signal[5:10] = 0.0
    proc = run(aman)
    assert list(np.flatnonzero(proc.transient_filter.dead)) == [5, 6, 7, 8, 9]
    assert found_flare(aman, proc, dataset)


def test_a_group_with_every_detector_cut_gives_an_empty_table(dataset):
    aman = load(dataset)
    aman.restrict("dets", aman.dets.vals[:0])
    proc = run(aman)
    table = proc_table(proc, aman.obs_info.obs_id)
    assert len(table) == 0 and set(FIRST) <= set(table.colnames)


def test_a_tod_shorter_than_one_scan_works(dataset):
    aman = load(dataset)
    start = aman.samps.offset + int((FLARE_TIME - 15) * 220)
    aman.restrict("samps", (start, start + 30 * 220))          # 30 s, no turnaround
    assert found_flare(aman, run(aman), dataset)


def test_no_candidates_gives_an_empty_table_with_the_full_schema(dataset):
    aman = load(dataset)
    steps = [dict(s) for s in STEPS]
    steps[1] = {"name": "transient_find", "calc": {"snr_threshold": 1e6}, "save": True}
    proc = core.AxisManager(aman.dets, aman.samps)
    for step in Pipeline(steps):
        step.process(aman, proc)
        step.calc_and_save(aman, proc)
    table = proc_table(proc, aman.obs_info.obs_id)
    assert len(table) == 0 and set(FIRST) <= set(table.colnames)
    assert str(table["flux"].unit) == "mJy" and str(table["ra"].unit) == "rad"


@pytest.mark.parametrize("field, step, message", [
    ("focal_plane", "transient_find", "focal_plane.xi"),
    ("boresight", "transient_filter", "boresight.az"),
])
def test_missing_fields_are_named_with_the_observation_and_group(dataset, field, step, message):
    aman = load(dataset)
    aman.move(field, None)
    with pytest.raises(ValueError) as err:
        run(aman)
    text = str(err.value)
    assert step in text and message in text
    assert aman.obs_info.obs_id in text and "w16" in text and "f090" in text


def test_unsorted_and_gapped_timestamps_are_refused(dataset):
    aman = load(dataset)
    aman.timestamps[[100, 101]] = aman.timestamps[[101, 100]]
    with pytest.raises(ValueError, match="not strictly increasing"):
        run(aman)
    aman = load(dataset)
    aman.timestamps[5000:] += 2.0
    with pytest.raises(ValueError, match="gaps"):
        run(aman)


def test_a_rerun_on_the_same_aman_keeps_every_candidate_and_hit(dataset):
    """Replacing transient_candidates/hits must not restrict the new ones to the old axes'
    lengths (the campaign reruns the steps on the same AxisManager)."""
    aman = load(dataset)
    run(aman)
    strict = Pipeline([{"name": "transient_find", "calc": {"snr_threshold": 4.0}}])[0]
    loose = Pipeline([{"name": "transient_find", "calc": {"snr_threshold": 2.5,
                                                           "min_dets": 1}}])[0]
    proc = core.AxisManager(aman.dets, aman.samps)
    strict.calc_and_save(aman, proc)
    n_strict = aman.transient_candidates.transient_cand.count
    loose.calc_and_save(aman, proc)
    cands, hits = aman.transient_candidates, aman.transient_hits
    assert cands.transient_cand.count > n_strict
    assert hits.transient_hit.count == int(np.sum(cands.n_samples))
    assert set(np.asarray(hits.cand)) == set(range(cands.transient_cand.count))
