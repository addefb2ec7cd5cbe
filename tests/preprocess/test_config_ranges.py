"""Every numeric config key of every step refuses a value it cannot use, when the pipeline is
built, with one line naming the step and the key."""
import dataclasses

import numpy as np
import pytest
from sotodlib.preprocess import Pipeline

import so_transients  # noqa: F401  registers the steps
from so_transients.common.step_config import ConfigError
from so_transients.preprocess.step_settings import step_configs

#: keys for which 0 is a documented setting: "off" or "none"
ZERO_ALLOWED = {"chi2_bins", "n_slides", "slide_groups", "seed", "edge_buffer", "mask_buffer",
                "turnaround_buffer", "chi2_mismatch"}


def numeric_keys():
    for step, classes in step_configs().items():
        for cls in classes:
            for f in dataclasses.fields(cls):
                if str(f.type).replace(" ", "").replace("|None", "") in ("float", "int"):
                    yield step, f.name, "int" in str(f.type)


@pytest.mark.parametrize("step, key, integer", list(numeric_keys()))
def test_a_negative_or_nan_value_is_refused_naming_step_and_key(step, key, integer):
    bad = [-1] + ([] if integer else [np.nan]) + ([] if key in ZERO_ALLOWED else [0])
    for value in bad:
        entry = {"name": step, "calc": {key: value}}
        if step == "transient_filter":
            entry = {"name": step, "process": {key: value}, "calc": True}
        elif step in ("transient_jumps", "transient_pca_mask", "transient_pca_filter",
                      "transient_fourier_filter"):
            entry = {"name": step, "process": {key: value}}
        with pytest.raises(ConfigError) as info:
            Pipeline([entry])
        assert step in str(info.value) and key in str(info.value), str(info.value)
