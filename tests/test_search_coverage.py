"""What a group's search covers: the searchable fraction is logged and archived (short
observations lose scans at the turnarounds), and whole-observation loads of several bands
keep every field the transient steps save."""
import logging

import numpy as np
import pytest

from conftest import load_group, run_sim, run_steps

STEPS = [{"name": "transient_filter", "process": {}, "calc": True, "save": True},
         {"name": "transient_find", "calc": {}, "save": True}]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return run_sim(tmp_path_factory.mktemp("coverage"), seed=5,
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
    with caplog.at_level(logging.INFO, logger="so_transients.processes"):
        proc = run(aman)
    fraction = np.asarray(proc.transient_find.searchable_fraction)
    assert len(fraction) == aman.dets.count and np.all(fraction == fraction[0])
    assert fraction[0] > 0.9
    assert any("searchable" in r.message and r.levelno == logging.INFO for r in caplog.records)


def test_a_short_observation_warns_that_it_loses_scans(dataset, caplog):
    """200 s of 90 s sweeps: the turnarounds, off-speed samples and their buffers leave less
    than half of the time searchable, which is logged as a warning and archived."""
    aman = load(dataset)
    with caplog.at_level(logging.INFO, logger="so_transients.processes"):
        proc = run(aman)
    assert np.asarray(proc.transient_find.searchable_fraction)[0] < 0.5
    assert any("short observation" in r.message and r.levelno == logging.WARNING
               for r in caplog.records)


@pytest.fixture(scope="module")
def two_band_dataset(tmp_path_factory):
    """130 s of w16, both MF bands, white noise only, a 3 Jy flare on p215A's path."""
    return run_sim(tmp_path_factory.mktemp("two_bands"), seed=9,
                   observation={"duration": 130.0},
                   atmosphere={"enabled": False}, cmb={"enabled": False},
                   flares={"list": [{"at_detector": "w16_f090_p215A", "at_time": 40.0,
                                     "t_peak": 40.0, "s_peak_mjy": 3000.0, "t_rise": 2.0}]})


SEARCH = [{"name": "transient_filter", "process": {}, "calc": True, "save": True},
          {"name": "transient_find", "calc": {}, "save": True},
          {"name": "transient_cuts", "calc": {}, "save": True},
          {"name": "transient_fit", "calc": {}, "save": True}]


def _flare_fit(aman, band):
    from so_transients.results import proc_table

    table = proc_table(run_steps(aman, SEARCH), aman.obs_info.obs_id)
    found = table[np.asarray(table["detected"], bool) & (table["bandpass"] == band)
                  & (np.abs(table["t_peak"] - (aman.timestamps[0] + 40.0)) < 1.0)]
    assert len(found) == 1
    return found[0]


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
