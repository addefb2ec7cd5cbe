"""The configuration of ``so-transients events``: one YAML, checked at the door.

Either an events YAML::

    preprocess: data/demo/preprocess.yaml   # the site config whose archive is read
    output: data/demo/events                # default: <archive folder>/../events
    nproc: 2
    association: {n_sigma: 5.0, min_separation_arcsec: 30.0, max_gap_s: 600.0}
    photometry: {before_s: 60.0, after_s: 60.0, detect_snr: 5.0, upper_limit_sigma: 3.0}
    lightcurve_fit: {fit_indices: false}
    spectral_min_snr: 3.0                   # crossings used for spectral indices
    catalogue: socat:///data/socat.db       # cross-match: a socat URL or an ECSV/CSV file
    crossmatch: {radius_per_jy_arcmin: 30.0, min_radius_arcmin: 1.5, flare_ratio: 5.0}

or the preprocess config itself (every other setting at its default). Defaults live in the
dataclasses only (:class:`so_transients.events.association.AssociationConfig`,
:class:`so_transients.detect.forced_fit.PhotometryConfig`,
:class:`so_transients.events.lightcurve_fit.FlareFitConfig`,
:class:`so_transients.sources.crossmatch.CrossmatchConfig`); the beam fit's window, radius and
error scale, and the scan-speed tolerance, are the site config's own ``transient_fit`` and
``transient_find`` settings, never configured again here.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import yaml

from so_transients.events.association import AssociationConfig
from so_transients.detect.find import FindConfig
from so_transients.detect.fit import FitConfig
from so_transients.detect.forced_fit import PhotometryConfig
from so_transients.events.lightcurve_fit import FlareFitConfig
from so_transients.site.pipeline import archive_index, read_config
from so_transients.common.step_config import ConfigError, from_yaml, setting
from so_transients.preprocess.step_settings import step_setting
from so_transients.sources.crossmatch import CrossmatchConfig


@dataclass
class EventsConfig:
    preprocess: Path = setting(unit="", doc="the site config whose archive is read")
    output: Path = setting(unit="", doc="the events folder (default: <archive folder>/../events)")
    nproc: int = setting(1, "", "worker processes")
    association: AssociationConfig = setting(
        default_factory=AssociationConfig, doc="detections into events and events into sources")
    photometry: PhotometryConfig = setting(
        default_factory=PhotometryConfig, doc="forced photometry: the light curves")
    lightcurve_fit: FlareFitConfig = setting(
        default_factory=FlareFitConfig, doc="the flare model fitted to each light curve")
    spectral_min_snr: float = setting(3.0, "", "crossings at this S/N or more give spectral indices")
    catalogue: str | None = setting(
        None, "", "known sources the events are cross-matched with: a socat URL (socat:, "
        "socat:///path/socat.db, sqlite:///..., postgresql://...) or an ECSV/CSV file; "
        "None: no cross-match")
    crossmatch: CrossmatchConfig = setting(
        default_factory=CrossmatchConfig, doc="the cross-match's radii and flare ratio")

    @property
    def site(self) -> dict:
        """The preprocess (site) config."""
        return read_config(self.preprocess)

    def step(self, name, cls):
        """The ``calc`` settings of site step ``name`` as its dataclass ``cls`` (defaults
        when the step is not in the config)."""
        for entry in self.site["process_pipe"]:
            if entry.get("name") == name:
                return step_setting(cls, entry.get("calc"), f"{self.preprocess}: {name}")
        return cls()

    @property
    def fit(self) -> FitConfig:
        return self.step("transient_fit", FitConfig)

    @property
    def find(self) -> FindConfig:
        return self.step("transient_find", FindConfig)


SECTIONS = {"association": AssociationConfig, "photometry": PhotometryConfig,
            "lightcurve_fit": FlareFitConfig, "crossmatch": CrossmatchConfig}


def _optional_str(value):
    return None if value is None else str(value)


def load_events_config(path, overrides=None) -> EventsConfig:
    """An :class:`EventsConfig` from an events YAML or a preprocess config (see the module);
    ``overrides``: {key: value} replacing top-level keys where the value is not None."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read the events config: {exc}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping of keys")
    if "archive" in raw:                     # a preprocess config
        raw = {"preprocess": str(path)}
    raw.update({k: v for k, v in (overrides or {}).items() if v is not None})
    known = {"preprocess", "output", "nproc", "spectral_min_snr", "catalogue", *SECTIONS}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {', '.join(unknown)}; expected some of "
                          f"{', '.join(sorted(known))}")
    if "preprocess" not in raw:
        raise ConfigError(f"{path}: needs `preprocess:` (the site config whose archive holds "
                          "the detections)")
    preprocess = Path(raw["preprocess"])
    read_config(preprocess)                  # refuses a file that is not a site config
    output = Path(raw.get("output") or archive_index(preprocess).parent.parent / "events")
    sections = {k: from_yaml(cls, raw.get(k), f"{path}: {k}") for k, cls in SECTIONS.items()}
    try:
        scalars = {k: cast(raw[k]) for k, cast in (("nproc", int), ("spectral_min_snr", float),
                                                   ("catalogue", _optional_str)) if k in raw}
        return EventsConfig(preprocess, output, **sections, **scalars)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: {exc}") from None
