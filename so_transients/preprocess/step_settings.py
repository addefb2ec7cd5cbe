"""Each transient step's config dataclasses, declared once, and a step's YAML block read
into them (for the processes, the campaign, the events command and the documentation).

``transient_find``'s block holds the keys of two dataclasses: the paper mode's
(:class:`~so_transients.detect.find.FindConfig`) and the coherent mode's
(:class:`~so_transients.coherent.config.CoherentConfig`).
"""
from __future__ import annotations

from so_transients.coherent.config import FIND_CONFIGS
from so_transients.common.step_config import ChunkConfig, from_yaml_parts
from so_transients.detect.cuts import CutsConfig
from so_transients.detect.common_mode import ExcursionConfig
from so_transients.detect.fit import FitConfig
from so_transients.detect.jumps import JumpConfig
from so_transients.detect.pca import PcaConfig
from so_transients.detect.matched_filter import FilterConfig
from so_transients.significance.far import SignificanceConfig

#: step name -> its config dataclasses (the keys of its YAML block are theirs)
STEP_CONFIGS = {
    "transient_jumps": (JumpConfig,),
    "transient_pca_mask": (ExcursionConfig,),
    "transient_pca_filter": (PcaConfig,),
    "transient_fourier_filter": (ChunkConfig,),
    "transient_glitches": (ChunkConfig,),
    "transient_filter": (FilterConfig,),
    "transient_find": FIND_CONFIGS,
    "transient_cuts": (CutsConfig,),
    "transient_significance": (SignificanceConfig,),
    "transient_fit": (FitConfig,),
}


def step_of(config_class) -> str:
    """The name of the step ``config_class`` configures."""
    for name, classes in STEP_CONFIGS.items():
        if config_class in classes:
            return name
    raise KeyError(f"{config_class.__name__} configures no transient step")


def step_setting(config_class, calc, where=None):
    """``config_class``'s settings from its step's YAML block ``calc`` (errors name
    ``where``, by default the step)."""
    name = step_of(config_class)
    classes = STEP_CONFIGS[name]
    return from_yaml_parts(classes, calc, where or name)[classes.index(config_class)]
