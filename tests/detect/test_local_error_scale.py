"""transient_fit's local error scale: a significant fit is refitted with the error scale
measured near it, in sweeps of its own scan direction, when that is larger (the noise is not
stationary)."""
import numpy as np
import pytest

from so_transients.common.step_config import ConfigError
from so_transients.detect import fit_candidates
from so_transients.detect.error_scale import ErrorScale
from so_transients.detect.fit import FitConfig


def test_only_significant_single_crossings_are_refitted_and_only_with_a_larger_scale(
        monkeypatch):
    cfg = FitConfig(local_window=30.0)
    cands = {"bandpass": np.array(["f090"] * 4), "t_median": np.array([10.0, 50.0, 90.0, 130.0]),
             "t_start": np.array([9.0, 49.0, 89.0, 100.0]),
             "t_stop": np.array([11.0, 51.0, 91.0, 160.0]),
             "cluster_ra": np.array([0.1, 0.2, 0.3, 0.4]), "cluster_dec": np.zeros(4),
             "n_crossings": np.array([1, 1, 1, 2])}
    rows = [dict(fit_ok=True, snr_fit=6.0, error_scale=1.5),    # significant: local 1.8
            dict(fit_ok=True, snr_fit=4.0, error_scale=1.5),    # not significant
            dict(fit_ok=True, snr_fit=5.5, error_scale=1.2),    # significant: local 1.1
            dict(fit_ok=True, snr_fit=9.0, error_scale=1.5)]    # a sweep stack
    directions = {10.0: 1, 50.0: 1, 90.0: -1, 130.0: -1}
    local = {10.0: 1.8, 90.0: 1.1}
    seen = []

    def measure(data, dets, sources, cfg_, direction, around=None):
        seen.append((around, direction, sorted(sources.t_lo)))
        return local[around]

    def refit(data, cands_, c, det_bands, scale, cfg_):
        used = scale.at(directions[cands_["t_median"][c]])
        return dict(fit_ok=True, snr_fit=rows[c]["snr_fit"] * rows[c]["error_scale"] / used,
                    error_scale=used)

    monkeypatch.setattr(fit_candidates, "measure_error_scale", measure)
    monkeypatch.setattr(fit_candidates, "_fit_one", refit)
    monkeypatch.setattr(fit_candidates, "_direction",
                        lambda data, cands_, c: directions[cands_["t_median"][c]])
    fit_candidates._local_scales(None, cands, np.array(["f090"]),
                                 {"f090": ErrorScale(1.5, 1.2)}, rows, cfg)
    # each in its own sweep direction, clear of every significant fit
    assert [s[:2] for s in seen] == [(10.0, 1), (90.0, -1)]
    assert seen[0][2] == [9.0, 89.0]
    assert rows[0]["error_scale"] == 1.8 and rows[0]["snr_fit"] == pytest.approx(5.0)
    assert rows[1]["snr_fit"] == 4.0
    assert rows[2]["error_scale"] == 1.2 and rows[2]["snr_fit"] == 5.5   # 1.1 is smaller
    assert rows[3]["error_scale"] == 1.5


def test_local_window_must_be_positive():
    with pytest.raises(ConfigError, match="local_window"):
        FitConfig(local_window=0.0)
    with pytest.raises(ConfigError, match="n_null_local"):
        FitConfig(n_null_local=0)


@pytest.mark.parametrize("value", [0.0, -1.0, [1.2], [1.2, 0.0], [1.0, 1.1, 1.2], "big"])
def test_a_fixed_error_scale_is_one_or_two_positive_numbers(value):
    if value == [1.2]:
        assert FitConfig(error_scale=value).error_scale == [1.2]
        return
    with pytest.raises(ConfigError, match="error_scale"):
        FitConfig(error_scale=value)
