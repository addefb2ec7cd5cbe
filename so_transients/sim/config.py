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
from so_transients.common.step_config import setting
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
    start: float = setting(1_700_000_000.0, "ctime", "start of the first observation")
    duration: float = setting(900.0, "s", "length of each observation")
    n_obs: int = setting(1, "", "consecutive observations (time blocks) per tube")
    gap: float = setting(60.0, "s", "time between consecutive observations")

    def __post_init__(self):
        if self.duration <= 0 or self.n_obs < 1 or self.gap < 0:
            raise ValueError("observation: duration must be > 0, n_obs >= 1 and gap >= 0")


@dataclass
class InstrumentConfig:
    tubes: list = setting(unit="", doc="LAT tube slots simulated", default_factory=lambda: ["i1"])
    wafers: list | None = setting(unit="", doc="wafers of those tubes; None: every wafer",
                                  default_factory=lambda: ["w16"])
    bands: list | None = setting(None, "", "bands simulated; None: both bands of each tube")

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
    enabled: bool = setting(True, "", "white and per-detector 1/f noise simulated")
    white_mjy: dict = setting(unit="mJy", doc="white-noise rms per sample, by band",
                              default_factory=lambda: dict(WHITE_NOISE_MJY))
    white_scatter: float = setting(0.0, "", "log-normal sigma of each detector's white-noise "
                                   "level (0: all equal)")
    fknee: Any = setting(None, "Hz", "each detector's own 1/f knee: a value or a [low, high] "
                         "log-uniform range; None: no per-detector 1/f")
    alpha: float = setting(1.0, "", "slope of the per-detector 1/f: P = P_white (fknee / f)^alpha")

    def __post_init__(self):
        if self.fknee is not None:
            self.fknee = _check_range("noise.fknee", self.fknee)
        if self.white_scatter < 0 or self.alpha <= 0:
            raise ValueError("noise: white_scatter must be >= 0 and alpha > 0")


@dataclass
class AtmosphereConfig:
    enabled: bool = setting(True, "", "a frozen turbulent atmosphere simulated")
    altitude: float = setting(1500.0, "m", "height of the frozen turbulent layer")
    outer_scale: float = setting(500.0, "m", "Kolmogorov outer scale")
    wind_speed: float = setting(8.0, "m/s", "speed of the layer")
    wind_direction: float = setting(30.0, "deg", "direction the layer moves to, from east "
                                    "towards north")
    aperture: float = setting(6.0, "m", "diameter of the near-field beam (the LAT primary)")
    pixel: float = setting(2.0, "m", "resolution of the screen")
    fknee: dict = setting(unit="Hz", doc="knee where the atmosphere's power is the white "
                          "noise's, by band",
                          default_factory=lambda: {b: PAPER_KNEE_HZ for b in WHITE_NOISE_MJY})


@dataclass
class CmbConfig:
    enabled: bool = setting(True, "", "a CMB sky simulated")
    resolution_arcmin: float = setting(1.0, "arcmin", "pixel size of the CMB map")


@dataclass
class FlareConfig:
    n: int = setting(0, "", "random flares, besides those listed")
    s_peak_mjy: Any = setting((300.0, 3000.0), "mJy", "peak flux at 93 GHz: a value or a "
                              "[low, high] log-uniform range")
    t_rise: Any = setting((0.5, 30.0), "s", "rise time: a value or a [low, high] log-uniform "
                          "range")
    t_decay: Any = setting(None, "s", "decay time, as t_rise; None: equal to the rise time")
    eta_rise: float = setting(1.0, "", "shape exponent of the rise (the paper's eq. 1)")
    eta_decay: float = setting(1.0, "", "shape exponent of the decay (the paper's eq. 1)")
    spectral_index: float = setting(0.0, "", "alpha of S ~ nu^alpha; s_peak_mjy is at 93 GHz")
    list: list = setting(unit="", doc="explicit flares (configs/sim_default.yaml)",
                         default_factory=list)

    def __post_init__(self):
        self.s_peak_mjy = _check_range("flares.s_peak_mjy", self.s_peak_mjy)
        self.t_rise = _check_range("flares.t_rise", self.t_rise)
        if self.t_decay is not None:
            self.t_decay = _check_range("flares.t_decay", self.t_decay)
        if self.n < 0:
            raise ValueError("flares.n must be >= 0")


@dataclass
class PointSourceConfig:
    n: int = setting(0, "", "random steady sources, besides those listed")
    flux_mjy: Any = setting((500.0, 5000.0), "mJy", "flux: a value or a [low, high] "
                            "log-uniform range")
    list: list = setting(unit="", doc="explicit sources (configs/sim_default.yaml)",
                         default_factory=list)

    def __post_init__(self):
        self.flux_mjy = _check_range("point_sources.flux_mjy", self.flux_mjy)


@dataclass
class GlitchConfig:
    enabled: bool = setting(False, "", "cosmic-ray glitches simulated")
    rate_per_hour: float = setting(30.0, "1/h", "events per wafer per hour")
    n_dets: Any = setting((5, 60), "", "detectors hit per event (both bands of the wafer): a "
                          "value or a [low, high] range")
    amplitude_mjy: Any = setting((3000.0, 30000.0), "mJy", "spike height: a value or a "
                                 "[low, high] range")
    time_constant: float = setting(0.004, "s", "exponential decay of each spike")

    def __post_init__(self):
        self.n_dets = [int(v) for v in _check_range("glitches.n_dets", self.n_dets)]
        self.amplitude_mjy = _check_range("glitches.amplitude_mjy", self.amplitude_mjy)


@dataclass
class DetectorYieldConfig:
    dead_fraction: float = setting(0.0, "", "fraction of each wafer-band's detectors that "
                                   "are dead")
    dead_mode: str = setting("zeros", "", "what a dead detector records: zeros, nan or constant")
    dead_value: float = setting(0.0, "mJy", "what it records with dead_mode: constant")
    noisy_fraction: float = setting(0.0, "", "fraction of each wafer-band's detectors that are "
                                    "noisy (never dead ones)")
    noisy_factor: float = setting(10.0, "", "their noise (white and 1/f) over their normal level")
    dead_noise: float = setting(0.0, "", "readout noise a dead detector still records, over the "
                                "band's white-noise level (0: none); with dead_mode zeros or "
                                "constant")
    lost_detectors: int = setting(0, "", "detectors of each wafer and band that record only NaN "
                                  "(a lost readout channel), drawn independently of dead and "
                                  "noisy ones")

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
    scatter: float = setting(0.0, "", "rms of each detector's true sky response over its "
                             "metadata's")
    distribution: str = setting("lognormal", "", "lognormal: exp(N(0, scatter)); gaussian: "
                                "1 + N(0, scatter)")

    def __post_init__(self):
        _check_choice("calibration.distribution", self.distribution, ("lognormal", "gaussian"))
        if self.scatter < 0:
            raise ValueError("calibration.scatter must be >= 0")


@dataclass
class TimeConstantConfig:
    tau_ms: Any = setting(None, "ms", "detector time constant: a value, a [low, high] "
                          "log-uniform range, or {band: value or range}; None: instantaneous")
    metadata_error: float = setting(0.0, "", "rms fractional error of det_cal's tau_eff "
                                    "(Gaussian)")
    metadata_nan: float = setting(0.0, "", "fraction of detectors whose det_cal tau_eff is NaN")

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
    sigma_arcsec: float = setting(0.0, "arcsec", "Gaussian error of the metadata xi and of "
                                  "eta (each axis)")

    def __post_init__(self):
        if self.sigma_arcsec < 0:
            raise ValueError("focal_plane_errors.sigma_arcsec must be >= 0")


@dataclass
class JumpConfig:
    rate_per_hour: float = setting(0.0, "1/h", "readout jumps per detector per hour")
    fraction: float = setting(0.0, "", "fraction of each wafer-band's detectors (dead ones "
                              "included) with ``count`` more jumps each, at random times")
    count: Any = setting(1, "", "jumps each of those detectors gets: a value or [low, high] "
                         "(uniform integers)")
    height: Any = setting((5.0, 50.0), "", "size in ``units``: a value or [low, high] "
                          "log-uniform; random sign")
    units: str = setting("white", "", "white: the detector's white-noise rms per sample; mjy")

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
    rate_per_hour: float = setting(0.0, "1/h", "NaN stretches per wafer and band per hour, "
                                   "each on one detector drawn at random (dead ones included)")
    duration: Any = setting((0.5, 5.0), "s", "their length: a value or [low, high] log-uniform")

    def __post_init__(self):
        self.duration = _check_range("gaps.duration", self.duration)
        if self.rate_per_hour < 0:
            raise ValueError("gaps.rate_per_hour must be >= 0")


@dataclass
class MovingSourceConfig:
    list: list = setting(unit="", doc="the moving sources (configs/sim_default.yaml)",
                         default_factory=list)


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
    seed: int = setting(0, "", "one integer fixes every random draw")
    output: str = setting("data/sim", "", "dataset folder")
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
