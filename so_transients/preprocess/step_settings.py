"""Each transient step's config dataclasses (its ``spec.configs``) and a step's YAML block
read into them (for the processes, the campaign, the events command and the documentation).

``transient_find``'s block holds the keys of two dataclasses: the paper mode's
(:class:`~so_transients.detect.find.FindConfig`) and the coherent mode's
(:class:`~so_transients.coherent.config.CoherentConfig`).
"""
from __future__ import annotations

from so_transients.common.step_config import from_yaml_parts
from so_transients.preprocess.step_fields import step_specs


def step_configs() -> dict:
    """``{step name: its config dataclasses}`` (the keys of its YAML block are theirs)."""
    return {name: spec.configs for name, spec in step_specs().items() if spec.configs}


def step_of(config_class) -> str:
    """The name of the step ``config_class`` configures."""
    for name, classes in step_configs().items():
        if config_class in classes:
            return name
    raise KeyError(f"{config_class.__name__} configures no transient step")


def step_setting(config_class, calc, where=None):
    """``config_class``'s settings from its step's YAML block ``calc`` (errors name
    ``where``, by default the step)."""
    name = step_of(config_class)
    classes = step_configs()[name]
    return from_yaml_parts(classes, calc, where or name)[classes.index(config_class)]
