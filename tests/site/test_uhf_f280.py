"""f280, the band no other test searches: a 2 Jy flare on UHF tube c1 (w00), through the
transient steps in both modes, is found once, where and as bright as it is."""
import numpy as np
import pytest

from so_transients.common import candidates
from so_transients.common.angles import ARCMIN, sky_separation

from tests.coherent.test_coherent_find import coherent_pipe
from tests.conftest import load_group, run_sim, run_steps
from tests.significance.test_significance import with_significance

pytestmark = pytest.mark.slow

FLARE = {"at_detector": "w00_f280_p120A", "at_time": 100.0, "t_peak": 100.0,
         "s_peak_mjy": 2000.0, "t_rise": 10.0}


@pytest.fixture(scope="module")
def uhf(module_tmp):
    return run_sim(module_tmp("uhf"), seed=31, observation={"duration": 180.0},
                   instrument={"tubes": ["c1"], "wafers": ["w00"], "bands": ["f280"]},
                   glitches={"enabled": True, "rate_per_hour": 200},
                   flares={"list": [FLARE]})


@pytest.mark.parametrize("mode", ["paper", "coherent"])
def test_an_f280_flare_is_found_once_at_its_place_and_flux(uhf, mode):
    aman = load_group(uhf, wafer="w00", band="f280")
    steps = [s for s in coherent_pipe() if s["name"] in candidates.STEPS
             or s["name"] == "transient_filter"]
    if mode == "paper":
        for s in steps:
            if s["name"] == "transient_find":
                s["calc"] = {**s["calc"], "mode": "paper"}
    else:
        steps = with_significance(steps)
    run_steps(aman, steps)
    cands = candidates.from_aman(aman.transient_candidates, candidates.CAND_AXIS)
    found = np.flatnonzero(np.asarray(cands["detected"], bool))
    truth = uhf.flares[uhf.flares["band"] == "f280"][0]
    assert len(found) == 1, (mode, cands["t_peak"][found] - truth["t_peak"])
    k = found[0]
    assert abs(cands["t_peak"][k] - truth["t_peak"]) < 0.5
    # f280's beam is 0.9' FWHM: the paper's f280 median offset is 9.1"; a 2 Jy crossing is
    # fitted at S/N ~ 40, an error of ~1", so 0.15' is ten errors and the paper's bound
    assert sky_separation(cands["ra"][k], cands["dec"][k], truth["ra"], truth["dec"]) \
        < 0.15 * ARCMIN
    # t_r = 10 s: the flux at the crossing is S_p; the f280 campaign's spread at t_r 5-15 s
    # is 7 % (docs/results/table2.md), 3 sigma of it
    assert abs(cands["flux"][k] / truth["s_peak"] - 1) < 0.21
