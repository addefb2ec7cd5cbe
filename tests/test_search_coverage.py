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
