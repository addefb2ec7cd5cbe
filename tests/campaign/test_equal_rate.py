"""Thresholds at the paper's false-detection rate: the noise tail model and the recount."""
import numpy as np
import pytest
from astropy.table import Table

from so_transients.campaign.equal_rate import (efficiency_at, equal_rate_thresholds,
                                               model_count_above, tail_threshold)


def _tail_sample(n, scale, x0, rng):
    """``n`` fitted S/N values above ``x0`` drawn from the model N(>x) ~ exp(-x^2 / 2 s^2)."""
    return np.sqrt(x0**2 + rng.exponential(2 * scale**2, n))


def test_the_tail_model_finds_the_threshold_of_a_known_tail():
    """400 noise candidates above S/N 4 in 10 wafer-band-hours with scale 1.2: the rate is
    0.08 per wafer-band-hour where x^2 = 16 + 2 (1.44) ln(400 / 0.8). The scale's estimate
    is an exponential mean of 400 draws (5 % error), which moves x by about 0.05 x ln(500)
    x 1.44 / x ~ 0.07 at x ~ 6.5: 4 sigma is 0.3."""
    rng = np.random.default_rng(3)
    snr = np.concatenate([_tail_sample(400, 1.2, 4.0, rng), rng.uniform(2, 4, 300)])
    x, scale, n_tail = tail_threshold(snr, 10.0, 0.08, x0=4.0)
    expected = np.sqrt(16 + 2 * 1.44 * np.log(400 / 0.8))
    assert n_tail == 400
    assert scale == pytest.approx(1.2, rel=4 * 0.05 / 2)
    assert x == pytest.approx(expected, abs=0.3)
    # the model reproduces the count above 5 within its Poisson error
    measured = np.sum(snr >= 5)
    assert model_count_above(5.0, snr, x0=4.0) == pytest.approx(measured, abs=4 * np.sqrt(measured))


def test_too_few_noise_candidates_leave_the_cut_where_it_is():
    x, _, n_tail = tail_threshold([4.5, 5.5, 3.0, 2.0], 3.0, 0.08)
    assert np.isnan(x) and n_tail == 2
    table = equal_rate_thresholds({"f220": [2.5, 3.2, 3.6]}, {"f220": 1.5}, n_boot=10)
    assert table["snr_threshold"][0] == 5.0 and table["basis"][0].startswith("fewer than 5")
    raised = equal_rate_thresholds({"f220": [2.5, 3.2, 6.5]}, {"f220": 1.5}, n_boot=10)
    assert raised["snr_threshold"][0] == pytest.approx(6.51)   # above the one that passed


def test_equal_rate_table_per_band_with_bootstrap_error():
    rng = np.random.default_rng(5)
    fitted = {"f090": _tail_sample(200, 1.0, 3.0, rng), "f150": _tail_sample(200, 1.5, 3.0, rng)}
    table = equal_rate_thresholds(fitted, {"f090": 3.0, "f150": 3.0}, n_boot=100)
    f090, f150 = (table[table["band"] == b][0] for b in ("f090", "f150"))
    assert f150["snr_model"] > f090["snr_model"]                 # heavier tail: higher cut
    assert f150["snr_threshold"] >= f150["snr_model"] and f150["snr_threshold"] >= 5
    assert 0 < f150["snr_threshold_err"] < 1.0
    assert f090["target_per_wbh"] == pytest.approx(2 / 24)


def test_outliers_above_the_model_raise_the_threshold_above_them():
    """A Gaussian-like tail plus two glitch residues at fitted S/N 8 and 9 in 3
    wafer-band-hours: the paper's rate allows 0.25 there, so the cut goes above 9."""
    rng = np.random.default_rng(7)
    snr = np.concatenate([_tail_sample(100, 1.0, 3.0, rng), [8.0, 9.0]])
    table = equal_rate_thresholds({"f090": snr}, {"f090": 3.0}, n_boot=20)
    assert table["snr_model"][0] < 8 and table["snr_threshold"][0] == pytest.approx(9.01)


def test_a_flare_counts_when_one_of_its_detections_reaches_the_threshold():
    flares = Table({"obs_id": ["o"] * 4, "band": ["f090"] * 4, "t_rise": [0.5] * 4,
                    "s_peak": [300.0] * 4, "source_id": [0, 1, 2, 3]})
    matched = Table({"obs_id": ["o"] * 4, "bandpass": ["f090"] * 4, "t_rise": [0.5] * 4,
                     "s_peak": [300.0] * 4, "source_id": [0, 0, 1, 2],
                     "snr_fit": [5.5, 7.2, 6.0, 5.1]})
    eff = efficiency_at(flares, matched, {"f090": 6.0})
    assert eff["injected"][0] == 4 and eff["detected"][0] == 2     # flares 0 (7.2) and 1 (6.0)
    assert efficiency_at(flares, matched, {"f090": 5.0})["detected"][0] == 3
