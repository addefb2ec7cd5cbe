"""Campaign statistics, matching tolerances, config checks and resume bookkeeping."""
import json

import numpy as np
import pytest
from astropy.table import Table

from so_transients.campaign.config import Cell, flux_grid, load_campaign
from so_transients.campaign.run import check_state, split_flares
from so_transients.campaign.stats import binomial_interval, monotone, threshold, thresholds
from so_transients.detect.matched_filter import FilterConfig, matched_filter
from so_transients.common.angles import ARCMIN
from so_transients.campaign.matching import match
from tests.detect.test_matched_filter import FS, SIGMA_T, red_noise

GRID = np.arange(100.0, 1000.0, 100.0)


def test_threshold_of_a_piecewise_linear_curve_is_exact():
    eff = np.clip((GRID - 100) / 800, 0, 1)      # 0 at 100 mJy, 1 at 900 mJy
    assert threshold(GRID, eff, 0.5) == pytest.approx(500.0)
    assert threshold(GRID, eff, 0.1) == pytest.approx(180.0)
    assert threshold(GRID, eff, 0.9) == pytest.approx(820.0)
    assert threshold(GRID, np.full(len(GRID), 0.95), 0.5) == 100.0   # already there
    assert np.isnan(threshold(GRID, np.full(len(GRID), 0.3), 0.5))   # never reached


def test_monotone_pools_adjacent_violators_with_weights():
    assert np.allclose(monotone([0, 0.3, 0.2, 0.6]), [0, 0.25, 0.25, 0.6])
    assert np.allclose(monotone([0, 0.3, 0.2, 0.6], [1, 1, 3, 1]), [0, 0.225, 0.225, 0.6])
    assert np.allclose(monotone([0.1, 0.5, 0.9]), [0.1, 0.5, 0.9])


def test_threshold_error_matches_binomial_noise_over_the_slope():
    """n = 400 flares per point on a slope of 1/800 per mJy: sigma_p = sqrt(p(1-p)/n) = 0.025
    at 50 %, so the 50 % threshold scatters by sigma_p / slope = 20 mJy."""
    rng = np.random.default_rng(3)
    n = np.full(len(GRID), 400)
    p = np.clip((GRID - 100) / 800, 0, 1)
    estimates, errors = [], []
    for _ in range(40):
        k = rng.binomial(n, p)
        best, err = thresholds(GRID, k, n, levels=(0.5,), n_boot=200, seed=1)[0.5]
        estimates.append(best)
        errors.append(err)
    spread = np.std(estimates)
    # 40 trials: the spread itself is known to ~ 1/sqrt(2 x 39) = 11 %
    assert 20 * 0.7 < spread < 20 * 1.3
    assert 20 * 0.7 < np.median(errors) < 20 * 1.3
    assert abs(np.mean(estimates) - 500) < 4 * 20 / np.sqrt(40)


def test_jeffreys_interval():
    eff, lo, hi = binomial_interval([0, 5, 10], [10, 10, 10])
    assert np.allclose(eff, [0, 0.5, 1])
    assert lo[0] == 0 and hi[2] == 1
    assert 0 < hi[0] < 0.2 and 0.8 < lo[2] < 1
    assert lo[1] == pytest.approx(1 - hi[1]) and 0.3 < lo[1] < 0.4


def _matching_case(dt, offset_arcmin):
    flares = Table(dict(source_id=[3], band=["f090"], ra=[1.0], dec=[0.0]))
    crossings = {(3, "obs", "w16", "f090"): np.array([100.0, 190.0])}
    det = Table(dict(bandpass=["f090"], obs_id=["obs"], wafer_slot=["w16"],
                     ra=[1.0 + offset_arcmin * ARCMIN], dec=[0.0], t_peak=[190.0 + dt]))
    return int(match(det, flares, crossings, max_dt=0.5, max_offset=0.5 * ARCMIN)["source_id"][0])


@pytest.mark.parametrize("dt, offset, expected", [
    (0.49, 0.0, 3), (-0.49, 0.0, 3), (0.51, 0.0, -1), (-0.51, 0.0, -1),
    (0.0, 0.49, 3), (0.0, 0.51, -1), (0.49, 0.49, 3), (0.51, 0.49, -1)])
def test_matching_tolerances_just_inside_and_outside(dt, offset, expected):
    assert _matching_case(dt, offset) == expected


def test_a_detection_in_another_wafer_or_band_does_not_match():
    flares = Table(dict(source_id=[3], band=["f090"], ra=[1.0], dec=[0.0]))
    crossings = {(3, "obs", "w16", "f090"): np.array([190.0])}
    det = Table(dict(bandpass=["f090", "f150"], obs_id=["obs", "obs"], wafer_slot=["w17", "w16"],
                     ra=[1.0, 1.0], dec=[0.0, 0.0], t_peak=[190.0, 190.0]))
    assert list(match(det, flares, crossings)["source_id"]) == [-1, -1]


def test_flux_grid_ranges_and_split_of_flares():
    assert flux_grid([{"start": 100, "stop": 1000, "step": 50}]) == list(np.arange(100., 1001., 50.))
    assert flux_grid([{"start": 100, "stop": 300, "step": 100}, 1250, 200]) == [100, 200, 300, 1250]
    with pytest.raises(ValueError):
        flux_grid([{"start": 100, "stop": 300, "step": 0}])
    assert split_flares(100, 3) == [34, 33, 33]
    assert Cell("f090", 0.5, 300.0).label == "f090_tr0.5_sp300"


def _config(tmp_path, **changes):
    data = {"output": str(tmp_path / "out"), "n_flares": 10,
            "simulation": {"observation": {"duration": 60.0}},
            "grid": {"f090": {"t_rise": [1.0], "s_peak_mjy": [300, 600]}}, **changes}
    path = tmp_path / "campaign.yaml"
    path.write_text(json.dumps(data))
    return load_campaign(path)


def test_bad_campaign_configs_are_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown campaign config keys"):
        _config(tmp_path, n_flare=3)
    with pytest.raises(ValueError, match="leave out flares"):
        _config(tmp_path, simulation={"flares": {"n": 2}})
    with pytest.raises(ValueError, match="unknown band"):
        _config(tmp_path, grid={"f100": {"s_peak_mjy": [1]}})
    with pytest.raises(ValueError, match="unknown keys in campaign section"):
        _config(tmp_path, injection={"pad": 3})


def test_resume_refuses_another_config_unless_restarted(tmp_path):
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    check_state(cfg, out)
    check_state(cfg, out)                      # the same config continues
    (out / "units").mkdir()
    (out / "units" / "x.flares.ecsv").write_text("")
    other = _config(tmp_path, n_flares=11)
    assert other.digest() != cfg.digest()
    with pytest.raises(ValueError, match="another config"):
        check_state(other, out)
    assert (out / "units" / "x.flares.ecsv").exists()
    check_state(other, out, restart=True)
    assert not (out / "units").exists()
    assert json.loads((out / "campaign.json").read_text())["digest"] == other.digest()
    # the output folder and process count do not change the digest
    assert _config(tmp_path, nproc=1).digest() == cfg.digest()


def test_the_filter_is_odd_so_inverted_data_give_minus_the_snr():
    """False positives on -TOD come from -S/N: the filter (bright-row refiltering included)
    must be exactly odd in the data."""
    rng = np.random.default_rng(5)
    tod = red_noise(rng, 6, 120 * 220)
    t = np.arange(tod.shape[1]) / FS
    tod[2] += (3000 * np.exp(-0.5 * ((t - 60) / SIGMA_T) ** 2)).astype(np.float32)
    cfg = FilterConfig(highpass=1.23)
    plus = matched_filter(tod, FS, SIGMA_T, cfg).snr
    minus = matched_filter(-tod, FS, SIGMA_T, cfg).snr
    assert np.abs(plus).max() > 10      # bright enough to be refiltered (S/N^2 / n_eff > 2 %)
    assert np.allclose(minus, -plus, atol=1e-5 * np.abs(plus).max())


def test_false_positive_rates_are_per_wafer_band_hour():
    """Three wafers of one band for 20 minutes each make one wafer-band-hour: 6 false
    detections there are 6 per wafer-band-hour but 18 per hour of the band's observation."""
    from so_transients.campaign.noise import Group
    from so_transients.campaign.report import false_positive_rates

    infos = {Group("obs", w, "f090"): {"duration": 1200.0, "n_false_noise": 2,
                                        "n_false_inverted": 1} for w in ("w16", "w17", "w18")}
    infos[Group("obs", "w16", "f150")] = {"duration": 1200.0, "n_false_noise": 0,
                                          "n_false_inverted": 0}
    table = false_positive_rates(infos)
    f090 = table[table["band"] == "f090"][0]
    assert f090["wafer_hours"] == pytest.approx(1.0) and f090["hours"] == pytest.approx(1 / 3)
    assert f090["rate_noise_per_wbh"] == pytest.approx(6.0)
    assert f090["rate_noise"] == pytest.approx(18.0)
    assert f090["rate_inverted_per_wbh"] == pytest.approx(3.0)
    f150 = table[table["band"] == "f150"][0]
    assert f150["rate_noise_per_wbh"] == 0 and f150["rate_noise_per_wbh_err"] == pytest.approx(3.0)


def test_the_full_check_runs_as_many_site_processes_as_memory_holds():
    from so_transients.campaign.full_check import site_processes

    hour_mf = 860 * 792_000 * 4                      # one hour-long MF group's signal, bytes
    assert site_processes(2, hour_mf, available=20 << 30) == 1
    assert site_processes(2, hour_mf // 6, available=20 << 30) == 2   # ten minutes
    assert site_processes(2, hour_mf, available=1 << 30) == 1         # never below one
