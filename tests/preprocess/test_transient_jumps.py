"""The transient_jumps step through sotodlib's Pipeline on a real wafer (every imperfection
at once, studies/configs/real_wafer.yaml): every +-5 Jy readout jump removed, on live and dead
channels, none invented, NaN samples left NaN, the counts in the archive's fields."""
import logging

import numpy as np
import pytest
from astropy.table import Table
from sotodlib import core
from sotodlib.preprocess import Pipeline

from so_transients.campaign.real_wafer import simulate_seed

pytestmark = pytest.mark.slow

PIPE = [{"name": "detrend", "process": {"method": "median"}},
        {"name": "transient_jumps", "process": {"threshold": 8.0, "window": 2.0},
         "save": True}]


@pytest.fixture(scope="module")
def wafer(module_tmp):
    root = module_tmp("jumps")
    sim = simulate_seed(root, seed=3, duration=180.0, flares=[])
    ctx = core.Context(str(sim.context))
    aman = ctx.get_obs(sim.obs_ids[0])
    logger = logging.getLogger("test_transient_jumps")
    Pipeline(PIPE[:1], logger=logger).run(aman)       # (detrend spreads a NaN to its row)
    nan_before = ~np.isfinite(np.asarray(aman.signal))
    proc = Pipeline(PIPE[1:], logger=logger).run(aman)[0]
    return root, aman, proc, nan_before


def test_every_jump_removed_and_none_invented(wafer):
    root, aman, proc, _ = wafer
    truth = Table.read(root / "truth" / "jumps.ecsv")
    ids = list(np.asarray(aman.det_info.readout_id))
    # a jump is a change of the median level over `window` s each side: one closer than that
    # (and a block) to either end cannot be told from the level there, and may or may not be
    fs = 1 / np.median(np.diff(aman.timestamps))
    margin = int((2.0 + 0.25) * fs)
    expected, unsure = np.zeros(len(ids), int), np.zeros(len(ids), int)
    for rid, sample in zip(truth["readout_id"], truth["sample"]):
        if str(rid) in ids:
            near_end = not margin <= sample < aman.samps.count - margin
            (unsure if near_end else expected)[ids.index(str(rid))] += 1
    found = np.asarray(aman.transient_n_jumps)
    assert expected.sum() >= 10                       # 3 % of the channels carry one
    assert np.all((found >= expected) & (found <= expected + unsure)), (
        np.flatnonzero((found < expected) | (found > expected + unsure)))
    assert np.array_equal(np.asarray(proc.transient_jumps.n_jumps), found)


def test_non_finite_samples_stay_non_finite(wafer):
    _, aman, _, nan_before = wafer
    assert nan_before.any()                           # the lost channel and the NaN stretch
    assert np.array_equal(~np.isfinite(np.asarray(aman.signal)), nan_before)
