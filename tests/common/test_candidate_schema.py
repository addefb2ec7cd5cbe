"""The candidate schema is the one declaration the steps, tables and documentation share."""

import numpy as np
import pytest

from so_transients.common import candidates
from so_transients.common.step_config import ConfigError, from_yaml
from so_transients.coherent.config import CoherentConfig
from so_transients.detect.cuts import CutsConfig
from so_transients.detect.find import FindConfig
from so_transients.detect.matched_filter import FilterConfig
from so_transients.significance.far import SignificanceConfig
from so_transients.detect.fit import FitConfig

def test_tables_carry_units_descriptions_and_unclipped_strings():
    rows = candidates.empty()
    rows = {k: np.zeros(1, v.dtype) for k, v in rows.items()}
    rows["cut_reason"] = np.array(["a_cut_reason_much_longer_than_twelve_characters"])
    table = candidates.table(rows)
    assert table["cut_reason"][0] == "a_cut_reason_much_longer_than_twelve_characters"
    assert str(table["flux"].unit) == "mJy" and table["flux"].description
    assert table.colnames == candidates.names(saved=True)


def test_by_band_keeps_long_strings_from_every_band():
    cands = {"bandpass": np.array(["f090", "f150", "f090"])}
    hits = {"cand": np.array([0, 1, 2]), "det": np.array([0, 1, 2])}
    out = candidates.by_band(cands, hits, lambda band, sel, c, h: {
        "reason": np.array(["x" * (20 if band == "f150" else 3)] * len(sel))}, "transient_cuts")
    assert list(out["reason"]) == ["xxx", "x" * 20, "xxx"]


@pytest.mark.parametrize("cls, cfg, message", [
    (FindConfig, {"snr_threshold": "abc"}, "transient_find: snr_threshold: expected float"),
    (FindConfig, {"min_dets": -3}, "transient_find: min_dets must be positive"),
    (FindConfig, {"min_det": 3}, "transient_find: unknown key(s) min_det (did you mean min_dets?)"),
    (FitConfig, {"n_null": 2.5}, "transient_fit: n_null: expected int"),
    # thresholds near 0 cluster most samples (a worker was killed at 22.6 GB at -3)
    (FindConfig, {"snr_threshold": -3.0}, "transient_find: snr_threshold must be at least 2"),
    (FindConfig, {"snr_threshold": 0}, "transient_find: snr_threshold must be at least 2"),
    (FilterConfig, {"highpass": -1.23}, "transient_filter: highpass must be a positive frequency"),
    (FilterConfig, {"min_noise_ratio": 0}, "transient_filter: min_noise_ratio must be positive"),
    (FilterConfig, {"max_excluded": 1.5}, "transient_filter: max_excluded must be at most 1"),
    # shares above 1 switch a test off without saying so
    (CoherentConfig, {"max_single_share": 1.5},
     "transient_find: max_single_share is a share and must be in (0, 1]"),
    (CoherentConfig, {"stack_max_share": 0}, "transient_find: stack_max_share must be positive"),
    (CutsConfig, {"pol_fraction": 2.0}, "transient_cuts: pol_fraction is a share"),
    (SignificanceConfig, {"max_single_share": 1.2},
     "transient_significance: max_single_share is a share"),
])
def test_bad_config_values_are_refused_with_the_step_and_key(cls, cfg, message):
    with pytest.raises(ConfigError) as err:
        from_yaml(cls, cfg, message.split(":")[0])
    assert message in str(err.value)


def test_yaml_units_are_converted_once():
    cfg = from_yaml(FindConfig, {"eps_arcmin": 1.5}, "transient_find")
    assert cfg.eps == pytest.approx(np.radians(1.5 / 60))
    assert from_yaml(FitConfig, {}, "transient_fit").radius == pytest.approx(np.radians(1.0))


@pytest.mark.parametrize("step, section, message", [
    ({"name": "transient_find", "calc": {"snr_threshold": "abc"}},
     "calc", "transient_find: snr_threshold: expected float, got 'abc'"),
    ({"name": "transient_find", "calc": {"min_dets": -3}},
     "calc", "transient_find: min_dets must be positive, got -3"),
    ({"name": "transient_cuts", "calc": {"min_aspect_ratoi": 2}},
     "calc", "transient_cuts: unknown key(s) min_aspect_ratoi"),
    ({"name": "transient_filter", "process": {"beam_fwhm_arcmin": {"f9O": 2.2}}},
     "process", "transient_filter: beam_fwhm_arcmin: unknown band(s) ['f9O']"),
    ({"name": "transient_fit", "calc": {"min_snr": "high"}},
     "calc", "transient_fit: min_snr: expected float"),
    ({"name": "transient_fit", "calc": ["min_snr", 5]},
     "calc", "transient_fit: the config block must be a mapping of keys"),
])
def test_the_pipeline_refuses_a_bad_step_config_when_it_is_built(step, section, message):
    """sotodlib builds the steps before reading any data: the error comes then, in one line
    naming the step and the key."""
    from sotodlib.preprocess import Pipeline

    import so_transients  # noqa: F401  registers the steps

    with pytest.raises(ConfigError) as err:
        Pipeline([step])
    assert message in str(err.value) and "\n" not in str(err.value)
