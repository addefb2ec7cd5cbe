"""Every setting a user writes in an events, alerts or simulation config carries its unit and
meaning in its dataclass field (``so_transients.common.step_config.setting``), as the steps'
do."""
import dataclasses

import pytest

from so_transients.alerts.records import AlertsConfig
from so_transients.detect.forced_fit import PhotometryConfig
from so_transients.events.association import AssociationConfig
from so_transients.events.config import EventsConfig
from so_transients.events.lightcurve_fit import FlareFitConfig
from so_transients.sim.config import SECTIONS, SimConfig
from so_transients.sources.crossmatch import CrossmatchConfig


SIM_SECTIONS = [SimConfig, *SECTIONS.values()]


@pytest.mark.parametrize("cls", [EventsConfig, AssociationConfig, PhotometryConfig,
                                 FlareFitConfig, CrossmatchConfig, AlertsConfig, *SIM_SECTIONS])
def test_each_setting_has_its_unit_and_meaning(cls):
    for f in dataclasses.fields(cls):
        if cls is SimConfig and f.name in SECTIONS:
            continue                     # a section: its own fields are checked
        assert f.metadata.get("doc"), f"{cls.__name__}.{f.name} has no meaning"
        assert "unit" in f.metadata, f"{cls.__name__}.{f.name} has no unit"
        for suffix, unit in (("_arcmin", "arcmin"), ("_arcsec", "arcsec"), ("_s", "s"),
                             ("_hz", "Hz"), ("_hours", "h"), ("_mjy", "mJy"), ("_ms", "ms"),
                             ("_per_hour", "1/h")):
            if f.name.endswith(suffix):
                assert f.metadata["unit"] == unit, f"{cls.__name__}.{f.name}"


def test_the_defaults_are_unchanged_by_their_metadata():
    """Nested sections default to their own dataclasses' defaults."""
    assert EventsConfig(preprocess="p.yaml", output="out").crossmatch == CrossmatchConfig()
    assert AlertsConfig().wafer_bands == 36
    assert SimConfig().observation.duration == 900.0 and SimConfig().instrument.wafers == ["w16"]
