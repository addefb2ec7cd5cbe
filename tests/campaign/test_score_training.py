"""Labels of the score's training candidates, and the flares it injects."""
import numpy as np
from astropy.table import Table

from so_transients.campaign.score_training import ScoreTrainingConfig, flare_list, label
from so_transients.common.angles import ARCMIN


def test_a_candidate_is_real_at_a_crossing_left_out_near_one_and_an_artefact_elsewhere():
    cfg = ScoreTrainingConfig(output="unused")
    ra0, dec0 = 1.0, -0.3
    flares = Table({"source_id": [7], "ra": [ra0], "dec": [dec0], "band": ["f090"]})
    crossings = {(7, "obs1", "w16", "f090"): np.array([100.0])}
    # at the crossing; 0.3 s and 0.3' off; 2 s off; 2' off; 10' off; another band
    dra = np.array([0.0, 0.3, 0.0, 2.0, 10.0, 0.0]) * ARCMIN / np.cos(dec0)
    t = np.array([100.0, 100.3, 102.0, 100.0, 100.0, 100.0])
    cands = Table({"obs_id": ["obs1"] * 6, "wafer_slot": ["w16"] * 6,
                   "bandpass": ["f090"] * 5 + ["f150"], "ra": ra0 + dra,
                   "dec": np.full(6, dec0), "t_peak": t})
    labels, source = label(cands, flares, crossings, cfg)
    assert list(labels) == [1, 1, -1, -1, 0, 0]
    assert list(source) == [7, 7, -1, -1, -1, -1]


def test_flares_are_drawn_over_the_configured_range_each_at_a_detector():
    cfg = ScoreTrainingConfig(output="unused")
    fl = flare_list(3, 600.0, 25, cfg.s_peak_mjy, cfg.t_rise)
    assert len(fl) == 25 and len({f["at_detector"] for f in fl}) == 25
    s = np.array([f["s_peak_mjy"] for f in fl])
    assert s.min() >= 150 and s.max() <= 3000 and s.max() / s.min() > 5
    times = np.sort([f["t_peak"] for f in fl])
    assert np.diff(times).min() > 15 and times[0] >= 20 and times[-1] <= 585
    assert {f["t_rise"] for f in fl} <= set(cfg.t_rise)
    assert flare_list(3, 600.0, 25, cfg.s_peak_mjy, cfg.t_rise) == fl      # one seed, one list
