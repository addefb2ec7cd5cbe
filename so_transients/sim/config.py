"""Simulation configuration: a YAML file read into validated dataclasses.

Every section and key is optional; defaults give one MF wafer (w16 in tube i1), both MF bands,
15 minutes at elevation 50 deg, white noise + atmosphere + CMB and a handful of flares. Unknown
keys are errors, so a typo never silently falls back to a default. See ``configs/sim_default.yaml``
for the documented full set.

The instrument's imperfections (dead and noisy detectors, per-detector noise, calibration errors,
time constants, focal-plane errors, readout jumps) and moving sources are all off by default, so
a config that does not name them gives exactly the ideal simulation.
"""
from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from so_transients.common.bands import HARDWARE_BAND_KEY, PAPER_KNEE_HZ, WHITE_NOISE_MJY
from so_transients.sim.scan import ScanPattern


def _is_number(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_integer(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _check_range(name, value, positive=True):
    """A number or a [low, high] range as [low, high] floats; errors say which rule failed."""
    if _is_number(value):
        value = [value, value]
    if not isinstance(value, (list, tuple)) or len(value) != 2 \
            or not all(_is_number(v) for v in value):
        raise ValueError(f"{name} must be a number or a [low, high] range of numbers, "
                         f"got {value!r}")
    if value[0] > value[1]:
        raise ValueError(f"{name}: a range is [low, high] with low <= high, got {list(value)}")
    if positive and value[0] <= 0:
        raise ValueError(f"{name} must be positive, got {list(value)}")
    return [float(v) for v in value]


#: What a field of each annotated type accepts: (check, what is expected, conversion).
_TYPES = {
    "float": (_is_number, "a number", float),
    "int": (_is_integer, "an integer", int),
    "bool": (lambda v: isinstance(v, bool), "true or false", bool),
    "str": (lambda v: isinstance(v, str), "a string", str),
    "list": (lambda v: isinstance(v, list), "a list", list),
    "dict": (lambda v: isinstance(v, dict), "a mapping", dict),
}


def _check_type(name, value, annotation):
    """``value`` of field ``name`` checked against its annotation (``"float"``, ``"int"``,
    ``"list | None"``...; ``Any`` and other types are checked by the section itself)."""
    options = [a.strip() for a in str(annotation).split("|")]
    if value is None and "None" in options:
        return value
    checks = [_TYPES[a] for a in options if a in _TYPES]
    if len(checks) != len([a for a in options if a != "None"]):
        return value
    for check, _, convert in checks:
        if check(value):
            return convert(value)
    expected = " or ".join(what for _, what, _ in checks)
    raise ValueError(f"{name} must be {expected}, got {value!r}")


@dataclass
class ObservationConfig:
    start: float = 1_700_000_000.0   # ctime of the first observation
    duration: float = 900.0          # seconds per observation
    n_obs: int = 1                   # consecutive observations per tube
    gap: float = 60.0                # seconds between consecutive observations

    def __post_init__(self):
        if self.duration <= 0 or self.n_obs < 1 or self.gap < 0:
            raise ValueError("observation: duration must be > 0, n_obs >= 1 and gap >= 0")


@dataclass
class InstrumentConfig:
    tubes: list = field(default_factory=lambda: ["i1"])
    wafers: list | None = field(default_factory=lambda: ["w16"])  # None: all wafers of the tubes
    bands: list | None = None                                      # None: both bands of each tube

    def __post_init__(self):
        if not self.tubes:
            raise ValueError("instrument.tubes must name at least one LAT tube slot")
        for band in self.bands or []:
            if band not in HARDWARE_BAND_KEY:
                raise ValueError(f"instrument.bands: unknown band {band!r}")


def _check_choice(name, value, choices):
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")


def _check_fraction(name, value):
    if not 0 <= value <= 1:
        raise ValueError(f"{name} must be in [0, 1], got {value}")


@dataclass
class NoiseConfig:
    enabled: bool = True
    white_mjy: dict = field(default_factory=lambda: dict(WHITE_NOISE_MJY))
    white_scatter: float = 0.0      # log-normal sigma of each detector's white-noise level
    fknee: Any = None               # Hz, each detector's own 1/f knee: a value or a [low, high]
                                    # log-uniform range; None: no per-detector 1/f
    alpha: float = 1.0              # slope of the per-detector 1/f

    def __post_init__(self):
        if self.fknee is not None:
            self.fknee = _check_range("noise.fknee", self.fknee)
        if self.white_scatter < 0 or self.alpha <= 0:
            raise ValueError("noise: white_scatter must be >= 0 and alpha > 0")


@dataclass
class AtmosphereConfig:
    enabled: bool = True
    altitude: float = 1500.0        # m, height of the frozen turbulent layer
    outer_scale: float = 500.0      # m, Kolmogorov outer scale
    wind_speed: float = 8.0         # m/s
    wind_direction: float = 30.0    # deg, direction the layer moves to, from +x (east) to +y
    aperture: float = 6.0           # m, diameter of the near-field beam (the LAT primary)
    pixel: float = 2.0              # m, screen resolution
    fknee: dict = field(default_factory=lambda: {b: PAPER_KNEE_HZ for b in WHITE_NOISE_MJY})


@dataclass
class CmbConfig:
    enabled: bool = True
    resolution_arcmin: float = 1.0


@dataclass
class FlareConfig:
    n: int = 0
    s_peak_mjy: Any = (300.0, 3000.0)   # a value or a [low, high] log-uniform range
    t_rise: Any = (0.5, 30.0)           # seconds, value or log-uniform range
    t_decay: Any = None                 # None: equal to t_rise
    eta_rise: float = 1.0
    eta_decay: float = 1.0
    spectral_index: float = 0.0         # S ~ nu^alpha; s_peak_mjy is at 93 GHz (f090)
    list: list = field(default_factory=list)  # explicit flares, see configs/sim_default.yaml

    def __post_init__(self):
        self.s_peak_mjy = _check_range("flares.s_peak_mjy", self.s_peak_mjy)
        self.t_rise = _check_range("flares.t_rise", self.t_rise)
        if self.t_decay is not None:
            self.t_decay = _check_range("flares.t_decay", self.t_decay)
        if self.n < 0:
            raise ValueError("flares.n must be >= 0")


@dataclass
class PointSourceConfig:
    n: int = 0
    flux_mjy: Any = (500.0, 5000.0)
    list: list = field(default_factory=list)

    def __post_init__(self):
        self.flux_mjy = _check_range("point_sources.flux_mjy", self.flux_mjy)


@dataclass
class GlitchConfig:
    enabled: bool = False
    rate_per_hour: float = 30.0          # events per wafer per hour
    n_dets: Any = (5, 60)                # detectors hit per event (both bands of the wafer)
    amplitude_mjy: Any = (3000.0, 30000.0)
    time_constant: float = 0.004         # s, exponential decay of each spike

    def __post_init__(self):
        self.n_dets = [int(v) for v in _check_range("glitches.n_dets", self.n_dets)]
        self.amplitude_mjy = _check_range("glitches.amplitude_mjy", self.amplitude_mjy)


@dataclass
class DetectorYieldConfig:
    dead_fraction: float = 0.0      # of the detectors of each wafer and band
    dead_mode: str = "zeros"        # what a dead detector records: zeros, nan or constant
    dead_value: float = 0.0         # mJy, with dead_mode: constant
    noisy_fraction: float = 0.0     # of the detectors of each wafer and band (never dead ones)
    noisy_factor: float = 10.0      # their noise (white and 1/f) over their normal level
    dead_noise: float = 0.0         # readout noise a dead detector still records, over the band's
    #                                 white-noise level (0: none); with dead_mode zeros or constant
    lost_detectors: int = 0         # detectors of each wafer and band that record only NaN (a lost
    #                                 readout channel), drawn independently of dead and noisy ones

    def __post_init__(self):
        _check_fraction("detector_yield.dead_fraction", self.dead_fraction)
        _check_fraction("detector_yield.noisy_fraction", self.noisy_fraction)
        if self.dead_fraction + self.noisy_fraction > 1:
            raise ValueError("detector_yield: dead_fraction + noisy_fraction must be <= 1")
        _check_choice("detector_yield.dead_mode", self.dead_mode, ("zeros", "nan", "constant"))
        if self.noisy_factor <= 0:
            raise ValueError("detector_yield.noisy_factor must be > 0")
        if self.dead_noise < 0 or self.lost_detectors < 0:
            raise ValueError("detector_yield.dead_noise and lost_detectors must be >= 0")


@dataclass
class CalibrationConfig:
    scatter: float = 0.0            # rms of each detector's true sky response over its metadata
    distribution: str = "lognormal" # lognormal: exp(N(0, scatter)); gaussian: 1 + N(0, scatter)

    def __post_init__(self):
        _check_choice("calibration.distribution", self.distribution, ("lognormal", "gaussian"))
        if self.scatter < 0:
            raise ValueError("calibration.scatter must be >= 0")


@dataclass
class TimeConstantConfig:
    tau_ms: Any = None              # None: instantaneous detectors; a value or [low, high]
                                    # log-uniform range, or {band: value or range}
    metadata_error: float = 0.0     # rms fractional error of det_cal's tau_eff (Gaussian)
    metadata_nan: float = 0.0       # fraction of detectors whose det_cal tau_eff is NaN

    def __post_init__(self):
        if isinstance(self.tau_ms, dict):
            for band in self.tau_ms:
                if band not in HARDWARE_BAND_KEY:
                    raise ValueError(f"time_constants.tau_ms: unknown band {band!r}")
            self.tau_ms = {b: _check_range(f"time_constants.tau_ms.{b}", v)
                           for b, v in self.tau_ms.items()}
        elif self.tau_ms is not None:
            self.tau_ms = _check_range("time_constants.tau_ms", self.tau_ms)
        if self.metadata_error < 0:
            raise ValueError("time_constants.metadata_error must be >= 0")
        _check_fraction("time_constants.metadata_nan", self.metadata_nan)

    def range_for(self, band):
        """[low, high] in ms for ``band``, or None (no time constant)."""
        if isinstance(self.tau_ms, dict):
            return self.tau_ms.get(band)
        return self.tau_ms


@dataclass
class FocalPlaneErrorConfig:
    sigma_arcsec: float = 0.0       # Gaussian error of the metadata xi and of eta (each axis)

    def __post_init__(self):
        if self.sigma_arcsec < 0:
            raise ValueError("focal_plane_errors.sigma_arcsec must be >= 0")


@dataclass
class JumpConfig:
    rate_per_hour: float = 0.0      # readout jumps per detector per hour
    fraction: float = 0.0           # of each wafer-band's detectors (dead ones included) with
    #                                 ``count`` more jumps each, at random times
    count: Any = 1                  # jumps each of those detectors gets: a value or [low, high]
    #                                 (uniform integers)
    height: Any = (5.0, 50.0)       # size: a value or [low, high] log-uniform; random sign
    units: str = "white"            # white: the detector's white-noise rms per sample; mjy

    def __post_init__(self):
        self.height = _check_range("jumps.height", self.height)
        self.count = [int(v) for v in _check_range("jumps.count", self.count)]
        if self.count[0] < 1:
            raise ValueError("jumps.count must be >= 1")
        _check_choice("jumps.units", self.units, ("white", "mjy"))
        _check_fraction("jumps.fraction", self.fraction)
        if self.rate_per_hour < 0:
            raise ValueError("jumps.rate_per_hour must be >= 0")

    @property
    def enabled(self) -> bool:
        return self.rate_per_hour > 0 or self.fraction > 0


@dataclass
class GapConfig:
    rate_per_hour: float = 0.0      # NaN stretches per wafer and band per hour, each on one
    #                                 detector drawn at random (dead ones included)
    duration: Any = (0.5, 5.0)      # s: a value or [low, high] log-uniform

    def __post_init__(self):
        self.duration = _check_range("gaps.duration", self.duration)
        if self.rate_per_hour < 0:
            raise ValueError("gaps.rate_per_hour must be >= 0")


@dataclass
class MovingSourceConfig:
    list: list = field(default_factory=list)  # see configs/sim_default.yaml


SECTIONS = {
    "observation": ObservationConfig, "instrument": InstrumentConfig, "scan": ScanPattern,
    "noise": NoiseConfig, "atmosphere": AtmosphereConfig, "cmb": CmbConfig,
    "flares": FlareConfig, "point_sources": PointSourceConfig, "glitches": GlitchConfig,
    "detector_yield": DetectorYieldConfig, "calibration": CalibrationConfig,
    "time_constants": TimeConstantConfig, "focal_plane_errors": FocalPlaneErrorConfig,
    "jumps": JumpConfig, "gaps": GapConfig, "moving_sources": MovingSourceConfig,
}


@dataclass
class SimConfig:
    seed: int = 0
    output: str = "data/sim"
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    instrument: InstrumentConfig = field(default_factory=InstrumentConfig)
    scan: ScanPattern = field(default_factory=ScanPattern)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    atmosphere: AtmosphereConfig = field(default_factory=AtmosphereConfig)
    cmb: CmbConfig = field(default_factory=CmbConfig)
    flares: FlareConfig = field(default_factory=FlareConfig)
    point_sources: PointSourceConfig = field(default_factory=PointSourceConfig)
    glitches: GlitchConfig = field(default_factory=GlitchConfig)
    detector_yield: DetectorYieldConfig = field(default_factory=DetectorYieldConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    time_constants: TimeConstantConfig = field(default_factory=TimeConstantConfig)
    focal_plane_errors: FocalPlaneErrorConfig = field(default_factory=FocalPlaneErrorConfig)
    jumps: JumpConfig = field(default_factory=JumpConfig)
    gaps: GapConfig = field(default_factory=GapConfig)
    moving_sources: MovingSourceConfig = field(default_factory=MovingSourceConfig)

    @classmethod
    def from_dict(cls, data: dict | None) -> "SimConfig":
        if data is not None and not isinstance(data, dict):
            raise ValueError(f"a simulation config is a mapping of keys and sections, got a "
                             f"{type(data).__name__}")
        data = dict(data or {})
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = set(data) - set(fields)
        if unknown:
            raise ValueError(f"unknown simulation config keys: {sorted(unknown)}")
        kwargs = {}
        for key, value in data.items():
            if key in SECTIONS:
                kwargs[key] = _section(key, SECTIONS[key], value)
            else:
                kwargs[key] = _check_type(key, value, fields[key].type)
        return cls(**kwargs)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _section(name, klass, value):
    """Section ``name`` as a ``klass``, each value checked against its field's type."""
    if value is not None and not isinstance(value, dict):
        raise ValueError(f"{name} must be a mapping of keys, got {value!r}")
    value = dict(value or {})
    fields = {f.name: f for f in dataclasses.fields(klass)}
    unknown = set(value) - set(fields)
    if unknown:
        raise ValueError(f"unknown keys in simulation config section {name!r}: {sorted(unknown)}; "
                         f"known: {sorted(fields)}")
    return klass(**{k: _check_type(f"{name}.{k}", v, fields[k].type) for k, v in value.items()})


def load_config(path=None, overrides: dict | None = None) -> SimConfig:
    """Read a simulation config (``None``: all defaults) and apply ``overrides`` (a top-level
    value replaces the config's; a section given as a dict updates the config's section key
    by key; None values are ignored). Every error is a one-line ValueError naming the file,
    the key and what is expected."""
    data = {}
    if path is not None:
        data = _read_yaml(path)
    for key, value in (overrides or {}).items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **{k: v for k, v in value.items() if v is not None}}
        elif isinstance(value, dict):
            data[key] = {k: v for k, v in value.items() if v is not None}
        elif value is not None:
            data[key] = value
    try:
        return SimConfig.from_dict(data)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path or 'simulation config'}: {exc}") from None


def _read_yaml(path) -> dict:
    """The YAML file ``path`` as a mapping (empty file: {})."""
    try:
        with open(Path(path)) as f:
            data = yaml.safe_load(f)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or "cannot be parsed"
        raise ValueError(f"{path}: not valid YAML{where}: {problem}") from None
    if data is not None and not isinstance(data, dict):
        raise ValueError(f"{path}: a simulation config is a mapping of keys and sections, "
                         f"got a {type(data).__name__}")
    return data or {}
