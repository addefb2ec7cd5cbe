"""Detection at a false-alarm budget: the background's far, its threshold, pooling, the
campaign's recount on ``map_z`` (coherent mode) or ``coherent_snr`` (paper mode)."""
from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table

from so_transients.campaign.equal_rate import efficiency_at
from so_transients.campaign.far_budget import (background_tables, band_budgets,
                                               budget_margin, budget_table, load_background,
                                               noise_far, pooled_backgrounds,
                                               save_background)
from so_transients.campaign.noise import Group
from so_transients.significance.far import Background, SignificanceConfig

ROOT = Path(__file__).resolve().parents[2]


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

    cfg = load_campaign(ROOT / "studies" / "configs" / "campaign_quick.yaml",
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
    from so_transients.common.step_config import ConfigError

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


def _stacking_background(seed=1):
    """A background whose search stacks sweeps: the inverted data's stacks have the same
    Gaussian-like tail, 100 per hour above Z = 3."""
    b = _background(seed=seed)
    b.stacks = _gaussian_maxima(b.data_hours, 100, np.random.default_rng(seed + 10))
    b.stack_slide_hours = 20 * b.data_hours
    slid = _gaussian_maxima(b.stack_slide_hours, 100, np.random.default_rng(seed + 20))
    b.stack_slides = slid[slid >= b.slide_floor]
    return b


def test_stacks_get_their_own_budget_and_half_the_rate_each(tmp_path):
    b = _stacking_background()
    budget = budget_table({"f090": b}, Table({"band": [], "map_z": [], "snr_fit": [],
                                              "detected": [], "n_crossings": []},
                                             dtype=("U8", float, float, bool, int)),
                          {"f090": 2.0})[0]
    # single crossings at half the paper's rate: their Z is higher than at the whole rate
    assert budget["z_budget"] == pytest.approx(b.threshold(1 / 24))
    assert budget["z_budget"] > b.threshold(2 / 24)
    # the stacks' budget: where their own far (inverted stacks, tail model) reaches it
    z_stack = budget["z_stack_budget"]
    assert b.stack_far(z_stack)["far"][0] <= 1 / 24 < b.stack_far(z_stack - 0.01)["far"][0]
    assert budget["n_stack_maxima"] == len(b.stacks)
    # saved, loaded and pooled with the stacks (and without: None, no stack budget)
    folders = {}
    for k, part in enumerate([b, _background(seed=2)]):
        (tmp_path / f"g{k}").mkdir()
        save_background(part, tmp_path / f"g{k}" / "background.npz", "s")
        folders[Group("obs", f"w{k}", "f090" if k == 0 else "f150")] = tmp_path / f"g{k}"
    loaded = load_background(tmp_path / "g0" / "background.npz")[0]
    assert np.array_equal(loaded.stacks, b.stacks)
    assert np.array_equal(loaded.stack_slides, b.stack_slides)
    assert loaded.stack_slide_hours == b.stack_slide_hours
    pooled = pooled_backgrounds(*background_tables(folders))
    assert np.array_equal(np.sort(pooled["f090"].stacks), np.sort(b.stacks))
    assert np.array_equal(np.sort(pooled["f090"].stack_slides), np.sort(b.stack_slides))
    assert pooled["f090"].stack_slide_hours == pytest.approx(b.stack_slide_hours)
    assert pooled["f150"].stacks is None and np.isnan(pooled["f150"].stack_far(5.0)["far"][0])


def test_each_detection_is_held_to_its_own_budget():
    """A sweep stack (n_crossings > 1) against the stacks' Z, a single crossing against the
    single crossings'; the noise-only check and far alike."""
    b = {"f090": _stacking_background()}
    z, z_stack, _ = band_budgets(b)["f090"]
    assert np.isfinite(z_stack) and z_stack != z
    low, high = min(z, z_stack), max(z, z_stack)
    table = Table({"band": ["f090"] * 2, "map_z": [high - 0.01] * 2, "snr_fit": [4.0] * 2,
                   "detected": [True] * 2, "n_crossings": [1, 4]})
    margin = budget_margin(table, "band", {"f090": "map_z"}, band_budgets(b))
    assert (margin >= 0).tolist() == [z == low, z_stack == low]
    far = noise_far(b, table)
    assert far["far"][1] == pytest.approx(b["f090"].stack_far(high - 0.01)["far"][0])
    assert far["far"][0] == pytest.approx(b["f090"].far(high - 0.01)["far"][0])


def test_crossings_within_the_stacking_window_are_injected_as_one_window():
    from so_transients.campaign.flare_injection import _stacked_runs
    from so_transients.sim.sources import SourceCrossing

    def run(lo, peak, dets):
        crossing = SourceCrossing(np.arange(3, 8), np.zeros(5), np.zeros(5),
                                  np.full(5, float(peak)))
        return np.array(dets), lo, lo + 10, [crossing]

    runs = [run(0, 10.0, [1, 2]), run(2000, 50.0, [2, 3]), run(3000, 20.0, [5]),
            run(9000, 40.0, [7])]
    merged = _stacked_runs(runs, window=4100)      # centred on the brightest, at 2005
    assert len(merged) == 2 and merged[1] is runs[3]
    dets, lo, hi, crossings = merged[0]
    assert dets.tolist() == [1, 2, 3, 5] and (lo, hi) == (0, 3010)
    # each crossing keeps its samples, now counted from the merged window's start
    assert [int(c.samples[0]) for c in crossings] == [3, 2003, 3003]
    assert sorted(r[1] for r in _stacked_runs(runs, window=3000)) == [0, 2000, 9000]  # 0 out
    assert _stacked_runs(runs[:1] + runs[3:], window=4100) == runs[:1] + runs[3:]


def test_a_detection_failing_the_chi2_test_is_held_to_every_maximums_budget(tmp_path):
    """Background maxima flagged by the chi-squared test: a detection that passes it is held
    to the Z of the maxima that pass (lower), one that fails to the Z of all of them, and
    the flags survive saving, tabling and pooling."""
    b = _background()
    b.slides_ok = b.slides < 4.5            # the slides' tail fails the test
    b.inverted_ok = b.inverted < 4.5
    path = tmp_path / "g" / "background.npz"
    path.parent.mkdir()
    save_background(b, path, "s")
    pooled = pooled_backgrounds(*background_tables({Group("obs", "w0", "f090"): path.parent}))
    z, _, z_failed = band_budgets(pooled)["f090"]
    assert z < z_failed
    assert z_failed == pytest.approx(_background().threshold(2 / 24))
    table = Table({"band": ["f090"] * 2, "map_z": [(z + z_failed) / 2] * 2,
                   "coherent_consistent": [True, False]})
    margin = budget_margin(table, "band", {"f090": "map_z"}, band_budgets(pooled))
    assert (margin >= 0).tolist() == [True, False]


def test_a_stacks_far_is_the_higher_of_its_slides_and_the_inverted_stacks():
    """Slid stacks count from the slides' floor over their own hours (an empty count gets
    half of one per live time); the inverted stacks over the data's; far is the higher."""
    b = Background(np.zeros(0), 0.0, np.zeros(0), 1.0, tail_from=None, slide_floor=4.5,
                   stacks=np.array([3.2, 4.0, 5.0]),
                   stack_slides=np.array([4.6, 4.8, 5.5, 6.0]), stack_slide_hours=20.0)
    far = b.stack_far([4.0, 4.7, 5.6, 7.0, np.nan])
    assert np.allclose(far["far_inverted"], [2.0, 1.0, 0.0, 0.0, np.nan], equal_nan=True)
    assert np.allclose(far["far_slides"], [np.nan, 3 / 20, 1 / 20, 0.5 / 20, np.nan],
                       equal_nan=True)
    assert np.allclose(far["far"], [2.0, 1.0, 1 / 20, 0.5 / 20, np.nan], equal_nan=True)
    # without stacking every rate is NaN
    plain = Background(np.zeros(0), 0.0, np.zeros(0), 1.0)
    assert all(np.isnan(v).all() for v in plain.stack_far([5.0]).values())
