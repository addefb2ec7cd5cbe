"""transient_fit's local error scale: a significant fit is refitted with the error scale
measured near it when that is larger (the noise is not stationary)."""
import numpy as np
import pytest

from so_transients.common.step_config import ConfigError
from so_transients.detect import fit_candidates
from so_transients.detect.fit import FitConfig


def test_only_significant_single_crossings_are_refitted_and_only_with_a_larger_scale(
        monkeypatch):
    cfg = FitConfig(local_window=30.0)
    cands = {"bandpass": np.array(["f090"] * 4), "t_median": np.array([10.0, 50.0, 90.0, 130.0]),
             "n_crossings": np.array([1, 1, 1, 2])}
    rows = [dict(fit_ok=True, snr_fit=6.0, error_scale=1.5),    # significant: local 1.8
            dict(fit_ok=True, snr_fit=4.0, error_scale=1.5),    # not significant
            dict(fit_ok=True, snr_fit=5.5, error_scale=1.5),    # significant: local 1.2
            dict(fit_ok=True, snr_fit=9.0, error_scale=1.5)]    # a sweep stack
    local = {10.0: 1.8, 90.0: 1.2}
    seen = []

    def measure(data, dets, times, cfg_, around=None):
        seen.append((around, sorted(times)))
        return local[around]

    def refit(data, cands_, c, det_bands, scales, cfg_):
        return dict(fit_ok=True, snr_fit=rows[c]["snr_fit"] * 1.5 / scales["f090"],
                    error_scale=scales["f090"])

    monkeypatch.setattr(fit_candidates, "measure_error_scale", measure)
    monkeypatch.setattr(fit_candidates, "_fit_one", refit)
    fit_candidates._local_scales(None, cands, np.array(["f090"]), {"f090": 1.5}, rows, cfg)
    assert [s[0] for s in seen] == [10.0, 90.0]
    assert seen[0][1] == [10.0, 90.0]          # away from every significant fit
    assert rows[0]["error_scale"] == 1.8 and rows[0]["snr_fit"] == pytest.approx(5.0)
    assert rows[1]["snr_fit"] == 4.0 and rows[2]["error_scale"] == 1.5
    assert rows[3]["error_scale"] == 1.5


def test_local_window_must_be_positive():
    with pytest.raises(ConfigError, match="local_window"):
        FitConfig(local_window=0.0)
    with pytest.raises(ConfigError, match="n_null_local"):
        FitConfig(n_null_local=0)
