"""What a group's search covers: the searchable fraction is logged and archived (short
observations lose scans at the turnarounds), and whole-observation loads of several bands
keep every field the transient steps save."""
import logging

import numpy as np
import pytest

from tests.conftest import load_group, run_sim, run_steps

STEPS = [{"name": "transient_filter", "process": {}, "calc": True, "save": True},
         {"name": "transient_find", "calc": {}, "save": True}]


@pytest.fixture(scope="module")
def dataset(module_tmp):
    return run_sim(module_tmp("coverage"), seed=5,
                   observation={"duration": 200.0}, instrument={"bands": ["f090"]},
                   atmosphere={"enabled": False}, cmb={"enabled": False})


load = load_group


def run(aman):
    return run_steps(aman, STEPS)


def test_a_stretch_of_constant_speed_is_searched_whole(dataset, caplog):
    aman = load(dataset)
    az = np.asarray(aman.boresight.az)
    middle = int(np.argmin(np.abs(az[: len(az) // 2] - np.median(az))))   # mid-sweep
    rate = 1 / np.median(np.diff(aman.timestamps))
    start = aman.samps.offset + middle - int(15 * rate)
    aman.restrict("samps", (start, start + int(30 * rate)))
    with caplog.at_level(logging.INFO, logger="so_transients.preprocess.processes"):
        proc = run(aman)
    fraction = np.asarray(proc.transient_find.searchable_fraction)
    assert len(fraction) == aman.dets.count and np.all(fraction == fraction[0])
    assert fraction[0] > 0.9
    assert any("searchable" in r.message and r.levelno == logging.INFO for r in caplog.records)


def _turnaround_window(aman, margin):
    """``aman`` restricted to its first turnaround (boresight slower than nominal) plus
    ``margin`` seconds of scanning on either side."""
    from so_transients.common.scan_geometry import constant_velocity

    bore = aman.boresight
    slow = np.flatnonzero(~constant_velocity(aman.timestamps, bore.az, bore.el))
    slow = slow[(slow > 10) & (slow < aman.samps.count - 10)]
    first_run = slow[: np.argmax(np.diff(slow) > 1) + 1] if np.any(np.diff(slow) > 1) else slow
    rate = 1 / np.median(np.diff(aman.timestamps))
    start = aman.samps.offset + first_run[0] - int(margin * rate)
    aman.restrict("samps", (start, start + len(first_run) + int(2 * margin * rate)))
    return aman


def test_a_stretch_of_mostly_turnaround_warns_that_little_is_searched(dataset, caplog):
    """A 3.1 s turnaround with 1 s of scanning on either side: only the scanning and the
    first and last ~0.15 s of the turnaround (within 10 % of the scan speed) are searched,
    less than half of the time, which is logged as a warning and archived."""
    aman = _turnaround_window(load(dataset), 1.0)
    with caplog.at_level(logging.INFO, logger="so_transients.preprocess.processes"):
        proc = run(aman)
    fraction = np.asarray(proc.transient_find.searchable_fraction)[0]
    assert 0.3 < fraction < 0.5
    assert any("searchable" in r.message and r.levelno == logging.WARNING
               for r in caplog.records)


def test_a_whole_observation_is_searched_up_to_the_turnarounds(dataset):
    """200 s of 90 s sweeps with 3.1 s turnarounds: everything but the turnarounds (and the
    first and last ~0.15 s of each, > 10 % off the scan speed) is searched."""
    fraction = np.asarray(run(load(dataset)).transient_find.searchable_fraction)[0]
    turnaround_share = 2 * (3.11 - 2 * 0.156) / 200.0
    assert fraction == pytest.approx(1 - turnaround_share, abs=0.005)


@pytest.fixture(scope="module")
def scan_end_dataset(module_tmp):
    """130 s of w16 f090, white noise only. The first sweep's constant-velocity part ends at
    86.89 s and the second's starts at 90 s (3.11 s turnaround, scan pattern defaults); two
    1.5 Jy flares (t_r = 1 s) are centred where p215A points 1 s before and 1 s after it."""
    flares = [{"at_detector": "w16_f090_p215A", "at_time": t, "t_peak": t,
               "s_peak_mjy": 1500.0, "t_rise": 1.0} for t in (85.89, 91.0)]
    return run_sim(module_tmp("scan_ends"), seed=13,
                   observation={"duration": 130.0}, instrument={"bands": ["f090"]},
                   atmosphere={"enabled": False}, cmb={"enabled": False},
                   flares={"list": flares})


@pytest.mark.parametrize("t_flare", [85.89, 91.0])
def test_a_crossing_one_second_from_a_turnaround_is_found(scan_end_dataset, t_flare):
    from so_transients.site.results import proc_table

    aman = load(scan_end_dataset)
    table = proc_table(run_steps(aman, SEARCH), aman.obs_info.obs_id)
    t0 = float(aman.timestamps[0])
    found = table[np.asarray(table["detected"], bool)
                  & (np.abs(table["t_peak"] - (t0 + t_flare)) < 0.5)]
    assert len(found) == 1
    assert found[0]["snr_fit"] > 10


@pytest.fixture(scope="module")
def two_band_dataset(module_tmp):
    """130 s of w16, both MF bands, white noise only, a 3 Jy flare on p215A's path."""
    return run_sim(module_tmp("two_bands"), seed=9,
                   observation={"duration": 130.0},
                   atmosphere={"enabled": False}, cmb={"enabled": False},
                   flares={"list": [{"at_detector": "w16_f090_p215A", "at_time": 40.0,
                                     "t_peak": 40.0, "s_peak_mjy": 3000.0, "t_rise": 2.0}]})


SEARCH = [{"name": "transient_filter", "process": {}, "calc": True, "save": True},
          {"name": "transient_find", "calc": {}, "save": True},
          {"name": "transient_cuts", "calc": {}, "save": True},
          {"name": "transient_fit", "calc": {}, "save": True}]


def _flare_fit(aman, band):
    from so_transients.site.results import proc_table

    table = proc_table(run_steps(aman, SEARCH), aman.obs_info.obs_id)
    found = table[np.asarray(table["detected"], bool) & (table["bandpass"] == band)
                  & (np.abs(table["t_peak"] - (aman.timestamps[0] + 40.0)) < 1.0)]
    assert len(found) == 1
    return found[0]


@pytest.mark.slow
@pytest.mark.parametrize("band", ["f090", "f150"])
def test_a_group_of_two_bands_fits_each_with_its_own_response(two_band_dataset, band):
    """SO groups by wafer (both bands in one group): each band's candidates are fitted with
    that band's filter response, so they match a group of that band alone."""
    from sotodlib import core

    ctx = core.Context(str(two_band_dataset.context))
    both = ctx.get_obs(two_band_dataset.obs_ids[0], dets={"wafer_slot": "w16"})
    joint = _flare_fit(both, band)
    summary = both.transient_filter
    rows = {b: np.flatnonzero(np.asarray(summary.bandpass) == b)[0] for b in ("f090", "f150")}
    width = {b: np.sum(np.asarray(summary.response)[r] > 0.5) for b, r in rows.items()}
    assert width["f150"] < width["f090"]          # the smaller beam crosses faster
    alone = _flare_fit(load_group(two_band_dataset, band=band), band)
    assert joint["flux"] == pytest.approx(alone["flux"], rel=1e-6)
    assert joint["flux_err"] / joint["error_scale"] == pytest.approx(
        alone["flux_err"] / alone["error_scale"], rel=1e-6)
    # the error scales differ only through their random null positions (the joint group's
    # nulls also avoid the other band's candidates): each is the MAD of 200 null fits,
    # 6 % precise, so their ratio is within 3 x sqrt(2) x 6 % = 25 %
    assert joint["error_scale"] == pytest.approx(alone["error_scale"], rel=0.25)
