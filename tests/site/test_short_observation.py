"""Short observations with the shipped site config: sotodlib's ``flag_turnarounds``
(``method: scanspeed``) needs two turnarounds; a shorter observation must end in a clear
result or a clear error naming it and its duration, never in a NaN traceback."""
from pathlib import Path

import numpy as np
import pytest
import yaml
from sotodlib import core
from sotodlib.tod_ops.flags import get_turnaround_flags

from so_transients import cli
from so_transients.campaign.matching import compare_with_truth
from so_transients.sim.scan import ScanPattern, boresight
from so_transients.site.pipeline import PAPER, PRODUCTION, TEMPLATE, write_site_config
from so_transients.site.results import read_catalogue
from so_transients.site.turnarounds import (
    MIN_TURNAROUNDS, count_turnarounds, scanspeed_steps, short_observations
)

from tests.conftest import run_sim

RATE = 220.0                                  # Hz, the MF sample rate
SHIPPED = yaml.safe_load(TEMPLATE.read_text())["process_pipe"]
FLAG_TURNAROUNDS = SHIPPED[scanspeed_steps(SHIPPED)[0]]


def scan_aman(duration, noise_rad=0.0, seed=0):
    """A detector-less AxisManager with the simulator's boresight over ``duration`` s."""
    n = int(round(duration * RATE))
    t = np.arange(n) / RATE
    az, el, _ = boresight(t, ScanPattern())
    az = az + np.random.default_rng(seed).normal(0, noise_rad, n) if noise_rad else az
    aman = core.AxisManager(core.LabelAxis("dets", ["d0"]), core.OffsetAxis("samps", n))
    aman.wrap("timestamps", t + 1.7e9, [(0, "samps")])
    bore = core.AxisManager(aman.samps)
    bore.wrap("az", az, [(0, "samps")])
    bore.wrap("el", el, [(0, "samps")])
    aman.wrap("boresight", bore)
    aman.wrap("flags", core.FlagManager.for_tod(aman))
    return aman


@pytest.mark.parametrize("duration, expected", [(60, 0), (120, 1), (178, 1), (180, 2),
                                                (600, 6)])
def test_turnarounds_of_the_simulated_scan(duration, expected):
    """Reversals at 88.4 s + k 90 s (90 s sweeps at el 50 deg, 1 deg/s^2); 2" of encoder
    noise (the boresight moves 25" per sample) adds none."""
    assert count_turnarounds(scan_aman(duration).boresight.az) == expected
    noisy = scan_aman(duration, noise_rad=np.radians(2 / 3600)).boresight.az
    assert count_turnarounds(noisy) == expected


@pytest.mark.parametrize("duration", [179.5, 181.0, 270.0, 600.0])
def test_what_the_check_passes_the_shipped_flag_turnarounds_can_flag(duration):
    """The shipped step's settings on the boresight alone: an observation with
    MIN_TURNAROUNDS turnarounds is flagged. (The check counts a reversal once the boresight
    moves back at half the scan speed, from 179.3 s here; sotodlib stops below 177.5 s and in
    between flags the whole first sweep as a turnaround.)"""
    aman = scan_aman(duration)
    assert count_turnarounds(aman.boresight.az) >= MIN_TURNAROUNDS
    get_turnaround_flags(aman, **FLAG_TURNAROUNDS["process"])


@pytest.mark.parametrize("duration", [100.0, 150.0, 177.0])
def test_what_the_check_refuses_stops_the_shipped_flag_turnarounds(duration):
    aman = scan_aman(duration)
    assert count_turnarounds(aman.boresight.az) < MIN_TURNAROUNDS
    with pytest.raises(ValueError, match="cannot convert float NaN to integer"):
        get_turnaround_flags(aman, **FLAG_TURNAROUNDS["process"])


@pytest.mark.parametrize("shipped", [PRODUCTION, PAPER], ids=lambda p: p.stem)
def test_the_shipped_configs_flag_turnarounds_by_scan_speed(shipped):
    pipe = yaml.safe_load(shipped.read_text())["process_pipe"]
    found = scanspeed_steps(pipe)
    assert len(found) == 1 and pipe[found[0]]["name"] == "flag_turnarounds"


def test_only_scanspeed_turnaround_steps_are_checked():
    assert scanspeed_steps([{"name": "flag_turnarounds", "process": {"t_buffer": 2.0}}]) == [0]
    assert scanspeed_steps([{"name": "flag_turnarounds", "process": {"method": "az"},
                             "calc": {"method": "az"}}]) == []
    assert scanspeed_steps([step for step in SHIPPED if step["name"] != "flag_turnarounds"]) \
        == []


@pytest.fixture(scope="module")
def short_run(module_tmp):
    """Two minutes of w16 at f090 with two bright flares, and the shipped config on it."""
    root = module_tmp("short")
    sim = run_sim(root / "data", seed=7, observation={"duration": 120.0},
                  instrument={"tubes": ["i1"], "wafers": ["w16"], "bands": ["f090"]},
                  flares={"n": 2, "s_peak_mjy": [2000, 3000], "t_rise": [2, 10]})
    config = write_site_config(sim.context.parent, path=root / "preprocess.yaml",
                               results=root / "preprocess")
    return sim, config


@pytest.mark.slow
def test_the_check_names_the_short_observation_and_its_duration(short_run):
    sim, config = short_run
    lines = short_observations(config)
    assert len(lines) == 1
    assert lines[0].startswith(f"{sim.obs_ids[0]}: 120 s with 1 turnaround(s)")
    assert "flag_turnarounds" in lines[0]


@pytest.mark.slow
def test_a_two_minute_observation_gives_its_flares_or_a_clear_error(short_run, capsys):
    """``so-transients run`` with the shipped config: either both flares detected, or a
    non-zero exit whose message names the observation and its duration. A line about NaN
    must be that message, not sotodlib's bare ``cannot convert float NaN to integer``."""
    sim, config = short_run
    code = cli.main(["run", str(config)])
    err = capsys.readouterr().err
    if code == 0:
        detections = read_catalogue(Path(config).parent / "preprocess" / "detections.ecsv")
        matched, flares, _ = compare_with_truth(sim.context.parent, detections)
        found = set(matched["source_id"][matched["source_id"] >= 0])
        assert found == set(flares["source_id"]), (found, list(flares["source_id"]))
    else:
        assert sim.obs_ids[0] in err and "120 s" in err and "flag_turnarounds" in err, err
        for line in err.splitlines():
            assert "NaN" not in line or "120 s" in line, line
