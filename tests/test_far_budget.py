"""Detection at a false-alarm budget: the background's far, its threshold, pooling, the
campaign's recount on ``map_z`` (coherent mode) or ``coherent_snr`` (paper mode)."""
from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table

from so_transients.campaign.equal_rate import efficiency_at
from so_transients.campaign.far_budget import (background_tables, budget_table,
                                               load_background, noise_far,
                                               pooled_backgrounds, save_background)
from so_transients.campaign.noise import Group
from so_transients.significance import Background, SignificanceConfig

ROOT = Path(__file__).resolve().parent.parent


def _gaussian_maxima(hours, rate_above_3, rng):
    """Maxima above Z = 3 whose tail is the Gaussian-like model with unit scale:
    N(>z) = n exp(-(z^2 - 9) / 2) for a Poisson number n (``rate_above_3`` per hour)."""
    n = rng.poisson(rate_above_3 * hours)
    return np.sqrt(9 + rng.exponential(2.0, n))


def _background(hours=2.0, slides=40, seed=1):
    rng = np.random.default_rng(seed)
    return Background(_gaussian_maxima(hours * slides, 300, rng), hours * slides,
                      _gaussian_maxima(hours, 300, rng), hours)


def test_the_budget_threshold_is_where_far_first_reaches_the_rate():
    b = _background()
    z = b.threshold(0.08)
    far = b.far([z - 0.01, z, z + 0.5])["far"]
    assert far[0] > 0.08 >= far[1] >= far[2]
    # the model: 300 per hour above 3, exp(-(z^2 - 9)/2) beyond: 0.08 per hour at
    # z = sqrt(9 + 2 ln(300 / 0.08)) = 5.05; the fitted scale's error over ~300 inverted
    # maxima (4 %) and the slides' count (3200 maxima in 80 h) move it by less than 0.2
    assert z == pytest.approx(np.sqrt(9 + 2 * np.log(300 / 0.08)), abs=0.2)


def test_a_background_too_short_for_the_rate_has_no_threshold():
    b = Background(np.array([3.5, 4.0]), 1.0, np.zeros(0), 0.5, tail_from=None)
    # no count above 4: far_slides rests on half a count in one hour, 0.5 > 0.08
    assert np.isnan(b.threshold(0.08))
    assert b.threshold(0.6) == pytest.approx(4.0, abs=0.01)


def test_pooled_backgrounds_add_live_time_and_keep_the_rate(tmp_path):
    parts = [_background(seed=s) for s in range(3)]
    folders = {}
    for k, part in enumerate(parts):
        (tmp_path / f"g{k}").mkdir()
        save_background(part, tmp_path / f"g{k}" / "background.npz", "stamp")
        folders[Group("obs", f"w{k}", "f090")] = tmp_path / f"g{k}"
    pooled = pooled_backgrounds(*background_tables(folders))["f090"]
    assert pooled.slide_hours == pytest.approx(3 * parts[0].slide_hours)
    assert pooled.data_hours == pytest.approx(3 * parts[0].data_hours)
    assert len(pooled.slides) == sum(len(p.slides) for p in parts)
    # the same noise three times over: the rate at Z = 4 agrees within Poisson errors
    one, three = parts[0].far(4.0)["far_slides"][0], pooled.far(4.0)["far_slides"][0]
    n = one * parts[0].slide_hours
    assert abs(three - one) < 4 * np.sqrt(n) / parts[0].slide_hours


def test_the_campaign_keeps_and_pools_each_groups_background(tmp_path):
    folders = {}
    for k, (wafer, band) in enumerate([("w16", "f090"), ("w17", "f090"), ("w16", "f150")]):
        folder = tmp_path / f"g{k}"
        folder.mkdir()
        save_background(_background(seed=k), folder / "background.npz", f"stamp{k}")
        folders[Group("obs", wafer, band)] = folder
    b, stamp = load_background(tmp_path / "g1" / "background.npz")
    assert stamp == "stamp1" and b.slide_hours == pytest.approx(80.0)
    maxima, live = background_tables(folders)
    pooled = pooled_backgrounds(maxima, live)
    assert sorted(pooled) == ["f090", "f150"]
    assert pooled["f090"].slide_hours == pytest.approx(160.0)
    assert pooled["f090"].data_hours == pytest.approx(4.0)
    assert np.array_equal(np.sort(pooled["f150"].inverted), np.sort(_background(seed=2).inverted))


def test_flares_and_noise_are_counted_at_the_budgets_z():
    b = {"f090": _background()}
    z = b["f090"].threshold(2 / 24)
    fitted = Table({"band": ["f090"] * 3, "map_z": [z + 1, z - 0.5, z + 0.2],
                    "snr_fit": [4.0, 3.5, 3.2], "detected": [True, True, False]})
    table = budget_table(b, fitted, {"f090": 2.0})
    row = table[0]
    assert row["z_budget"] == pytest.approx(z)
    assert row["n_noise_above"] == 1               # the third is above, but not detected
    assert row["expected_above"] == pytest.approx(2 / 24 * 2.0)
    far = noise_far(b, fitted)
    assert len(far) == 2 and far["far"][0] <= 2 / 24 < far["far"][1]
    # a flare counts when one of its detections reaches the budget's Z, whatever its fit S/N
    flares = Table({"obs_id": ["o"] * 2, "band": ["f090"] * 2, "t_rise": [0.5] * 2,
                    "s_peak": [300.0] * 2, "source_id": [0, 1]})
    matched = Table({"obs_id": ["o"] * 3, "bandpass": ["f090"] * 3, "t_rise": [0.5] * 3,
                     "s_peak": [300.0] * 3, "source_id": [0, 0, 1],
                     "snr_fit": [3.3, 9.0, 4.0], "map_z": [z + 0.1, z - 1.0, z - 0.1]})
    assert efficiency_at(flares, matched, {"f090": z}, column="map_z")["detected"][0] == 1
    assert efficiency_at(flares, matched, {"f090": 5.0})["detected"][0] == 1


def test_a_background_too_short_for_the_budget_is_named(caplog):
    short = {"f150": Background(np.array([3.5, 4.0]), 1.0, np.zeros(0), 0.5, tail_from=None)}
    fitted = Table({"band": ["f150"], "map_z": [5.0], "snr_fit": [4.0], "detected": [True]})
    table = budget_table(short, fitted, {"f150": 0.5})
    assert np.isnan(table["z_budget"][0]) and table["n_noise_above"][0] == 0
    assert "f150" in caplog.text and "cannot resolve" in caplog.text


@pytest.mark.parametrize("mode, far_budget, statistic", [
    ("paper", None, None), ("paper", True, "coherent_snr"), ("coherent", None, "map_z"),
    ("coherent", False, None)])
def test_the_budget_ranks_each_mode_by_its_coherent_statistic(mode, far_budget, statistic):
    from so_transients.campaign.config import load_campaign

    cfg = load_campaign(ROOT / "configs" / "campaign_quick.yaml",
                        {"preprocess_overrides": {"transient_find": {"calc": {"mode": mode}}}})
    cfg.far_budget = far_budget            # (the quick campaign sets it)
    assert cfg.far_statistic() == statistic
    names = [s["name"] for s in cfg.pipeline_steps()[1]]
    if statistic == "coherent_snr":
        # the paper mode's candidates get their Z before the fit, without slides or a cut
        assert names == ["transient_find", "transient_cuts", "transient_significance",
                         "transient_fit"]
        calc = cfg.pipeline_steps()[1][2]["calc"]
        assert calc["n_slides"] == 0 and calc["max_far"] is None
    else:
        assert "transient_significance" not in names


def test_slides_cannot_be_negative():
    from so_transients.step_config import ConfigError

    assert SignificanceConfig(n_slides=0).n_slides == 0
    with pytest.raises(ConfigError, match="transient_significance: n_slides"):
        SignificanceConfig(n_slides=-1)


def test_combined_campaigns_rank_each_band_by_its_own_statistic():
    """A coherent campaign's band (written before the ``statistic`` column: masked once
    stacked) and a paper-mode one's, as ``campaign-combine`` stacks them."""
    from astropy.table import vstack

    from so_transients.campaign.far_budget import band_statistic, live_statistics

    old = Table({"band": ["f090"], "slide_hours": [1.0]})
    new = Table({"band": ["f150"], "slide_hours": [1.0], "statistic": ["coherent_snr"]})
    statistics = live_statistics(vstack([old, new]))
    assert statistics == {"f090": "map_z", "f150": "coherent_snr"}
    rows = vstack([Table({"bandpass": ["f090", "f150"], "map_z": [7.0, np.nan]}),
                   Table({"bandpass": ["f150"], "map_z": [np.nan], "coherent_snr": [6.0]})])
    # a band's values come from its own column; missing (masked) values are NaN, not 0
    assert np.array_equal(band_statistic(rows, "bandpass", statistics), [7.0, np.nan, 6.0],
                          equal_nan=True)
