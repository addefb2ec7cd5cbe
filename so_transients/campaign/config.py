"""Injection-recovery campaign configuration: a YAML file read into a validated dataclass.

A campaign names a noise-only simulation (the ``simulation`` section, the schema of
``so-transients simulate`` without flares), the site preprocess config whose steps run on it,
and a grid of bands x rise times x peak fluxes with ``n_flares`` flares per cell. See
``studies/configs/campaign_quick.yaml`` for the documented full set.

The config's hash (:meth:`CampaignConfig.digest`) labels everything the campaign writes, so a
resumed run never mixes results of different configs.
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from so_transients.common.bands import WHITE_NOISE_MJY
from so_transients.detect.find import FindConfig
from so_transients.sim.config import SimConfig
from so_transients.sim.sources import PLACEMENTS
from so_transients.significance.far import SignificanceConfig
from so_transients.site.pipeline import PAPER, REPOSITORY, apply_overrides
from so_transients.common.step_config import from_yaml
from so_transients.campaign.search_steps import split_pipe, step_settings, with_coherent_snr

#: Rise times of the paper's grid (section 5.1), seconds.
PAPER_RISE_TIMES = (0.5, 1.0, 2.5, 5.0, 15.0, 30.0, 150.0, 300.0)


def flux_grid(spec) -> list:
    """Peak fluxes (mJy) from a list, or from ``[{start, stop, step}, ...]`` ranges (inclusive)."""
    values = []
    for item in spec if isinstance(spec, list) else [spec]:
        if isinstance(item, dict):
            unknown = set(item) - {"start", "stop", "step"}
            if unknown or item.get("step", 0) <= 0:
                raise ValueError(f"a flux range needs start, stop and a positive step: {item}")
            n = int(np.floor((item["stop"] - item["start"]) / item["step"] + 1e-9)) + 1
            values += list(item["start"] + item["step"] * np.arange(n))
        else:
            values.append(item)
    values = sorted({float(v) for v in values})
    if not values or values[0] <= 0:
        raise ValueError(f"peak fluxes must be positive, got {spec}")
    return values


@dataclass(frozen=True)
class Cell:
    """One grid cell: band, rise time (= decay time, s) and peak flux (mJy)."""

    band: str
    t_rise: float
    s_peak: float

    @property
    def label(self) -> str:
        return f"{self.band}_tr{self.t_rise:g}_sp{self.s_peak:g}"


@dataclass
class Matching:
    max_dt: float = 0.5              # s, to a moment the group crossed the flaring source
    max_offset_arcmin: float = 0.5


@dataclass
class Injection:
    """How flares are placed, injected and searched.

    ``placement``: ``detector_at_peak`` puts each flare where a random detector of the band
    points at the flare's peak time (the peak is always sampled); ``scan_area`` where one points
    at an independent random constant-velocity time (anywhere in the scanned area: the peak is
    usually not sampled, as for the paper's example flare); ``active_window`` where one points
    at a time uniform within the flare's active window (the array meets the flare at a random
    phase of its light curve). The peak time is uniform in the constant-velocity part in every
    case. ``flare_eta``: the power-law index of eq. 1's rise and decay (1: linear; the paper
    does not state its value; larger makes the flare more peaked)."""

    window_pad: float = 3.0          # s of data kept on each side of a crossing
    filter_pad: float = 10.0         # s of zero padding when filtering the injected signal
    strip_sigma: float = 10.0        # detectors within this many beam sigmas of the track
    min_expected_snr: float = 0.5    # skip crossings whose best detector expects less S/N
    max_crossings: int | None = None  # per flare and group, brightest first (None: all)
    placement: str = "detector_at_peak"   # or "scan_area", "active_window" (see above)
    flare_eta: float = 1.0           # power-law index of the rise and decay (eq. 1)

    def __post_init__(self):
        if self.placement not in PLACEMENTS:
            raise ValueError(f"campaign injection placement {self.placement!r}: "
                             f"use one of {PLACEMENTS}")
        if not self.flare_eta > 0:
            raise ValueError(f"campaign injection flare_eta must be > 0, got {self.flare_eta}")


@dataclass
class FullCheck:
    """Cells re-run through the full site pipeline (flares injected in the TOD) to compare."""

    cells: list = field(default_factory=list)   # [{band, t_rise, s_peak_mjy}, ...]
    n_flares: int = 30
    separation: float = 20.0         # s between one flare's end and the next one's start


@dataclass
class CampaignConfig:
    output: str = "data/campaign"
    seed: int = 0
    nproc: int = 2                   # worker processes (or MPI ranks) for the injections
    n_flares: int = 100              # flares per cell and band
    simulation: dict = field(default_factory=dict)
    preprocess: str = str(PAPER)
    preprocess_overrides: dict = field(default_factory=dict)
    grid: dict = field(default_factory=dict)    # band -> {t_rise: [...], s_peak_mjy: [...]}
    matching: Matching = field(default_factory=Matching)
    injection: Injection = field(default_factory=Injection)
    full_check: FullCheck = field(default_factory=FullCheck)
    inverted: bool = True            # also count false positives on sign-inverted data
    far_budget: bool | None = None   # detect at the paper's rate by the coherent Z's far
    #                                  (None: in coherent mode; see far_statistic)

    def __post_init__(self):
        self.sim = SimConfig.from_dict({"seed": self.seed, **self.simulation})
        if self.sim.flares.n or self.sim.flares.list:
            raise ValueError("campaign simulation: leave out flares; the campaign injects them")
        if not self.grid:
            raise ValueError("campaign: the grid names no band")
        self.cells = []
        for band, spec in self.grid.items():
            if band not in WHITE_NOISE_MJY:
                raise ValueError(f"campaign grid: unknown band {band!r}")
            unknown = set(spec) - {"t_rise", "s_peak_mjy"}
            if unknown:
                raise ValueError(f"campaign grid {band}: unknown keys {sorted(unknown)}")
            rises = [float(t) for t in spec.get("t_rise", PAPER_RISE_TIMES)]
            if min(rises) <= 0:
                raise ValueError(f"campaign grid {band}: rise times must be positive")
            self.cells += [Cell(band, t, s) for t in rises for s in flux_grid(spec["s_peak_mjy"])]
        if self.n_flares < 1 or self.nproc < 1:
            raise ValueError("campaign: n_flares and nproc must be >= 1")
        if not Path(self.preprocess).exists():
            raise FileNotFoundError(f"campaign preprocess config {self.preprocess} not found")
        with open(self.preprocess) as f:
            self.process_pipe = yaml.safe_load(f)["process_pipe"]   # read once

    @property
    def bands(self) -> list:
        return sorted(self.grid)

    @property
    def check_cells(self) -> list:
        return [Cell(c["band"], float(c["t_rise"]), float(c["s_peak_mjy"]))
                for c in self.full_check.cells]

    def digest(self) -> str:
        """Hash of everything that changes results (not the output folder or process count).
        The default flare placement, light-curve index and false-alarm budget are left
        out, so configs written before them keep their hash."""
        data = dataclasses.asdict(self)
        data.pop("output")
        data.pop("nproc")
        for key in ("placement", "flare_eta"):
            if getattr(self.injection, key) == getattr(Injection(), key):
                data["injection"].pop(key)
        if self.far_budget is None:
            data.pop("far_budget")
        data["preprocess"] = self.process_pipe
        text = json.dumps(data, sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def sim_digest(self) -> str:
        """Hash of what the noise-only simulation depends on."""
        text = json.dumps([self.simulation, self.seed], sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def noise_digest(self) -> str:
        """Hash of what the noise-only observations depend on (simulation and preprocessing;
        and whether their search gives ``coherent_snr``, a paper-mode false-alarm budget)."""
        parts = [self.simulation, self.seed, self.process_pipe, self.preprocess_overrides]
        if self.far_statistic() == "coherent_snr":
            parts.append("coherent_snr")
        text = json.dumps(parts, sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def significance_settings(self):
        """``transient_significance``'s settings in the preprocess config (with the
        overrides), or its defaults where the step is not listed: the background of the
        campaign's false-alarm budget (:mod:`.far_budget`)."""
        entry = next((s for s in self._pipe() if s["name"] == "transient_significance"),
                     (self.preprocess_overrides or {}).get("transient_significance", {}))
        return from_yaml(SignificanceConfig, entry.get("calc"), "transient_significance")

    def pipeline_steps(self):
        """(standard steps through transient_filter, search steps) of the preprocess config,
        with the campaign's overrides applied (fresh copies: callers may change them). With a
        false-alarm budget in paper mode the search steps also give every candidate its
        ``coherent_snr`` (:func:`.search_steps.with_coherent_snr`)."""
        standard, search = split_pipe(self._pipe())
        if self.far_statistic() == "coherent_snr":
            search = with_coherent_snr(search, self.significance_settings())
        return standard, search

    def far_statistic(self):
        """What the false-alarm budget (:mod:`.far_budget`) ranks detections by: ``map_z``
        in coherent mode, ``coherent_snr`` in paper mode, None without a budget
        (``far_budget``; by default a budget in coherent mode only)."""
        coherent = step_settings(split_pipe(self._pipe())[1], FindConfig).mode == "coherent"
        if not (coherent if self.far_budget is None else self.far_budget):
            return None
        return "map_z" if coherent else "coherent_snr"

    def _pipe(self) -> list:
        """A fresh copy of the preprocess config's steps with the campaign's overrides."""
        return apply_overrides(copy.deepcopy(self.process_pipe), self.preprocess_overrides)


SECTIONS = {"matching": Matching, "injection": Injection, "full_check": FullCheck}


def load_campaign(path, overrides: dict | None = None) -> CampaignConfig:
    """Read a campaign YAML; unknown keys are errors. Relative ``preprocess`` paths are taken
    from the repository root when they do not exist relative to the working directory."""
    with open(path) as f:
        data = yaml.safe_load(f) or {}
    data.update({k: v for k, v in (overrides or {}).items() if v is not None})
    known = {f.name for f in dataclasses.fields(CampaignConfig)}
    unknown = set(data) - known
    if unknown:
        raise ValueError(f"unknown campaign config keys: {sorted(unknown)}; known: {sorted(known)}")
    for name, klass in SECTIONS.items():
        if name in data:
            section = dict(data[name] or {})
            bad = set(section) - {f.name for f in dataclasses.fields(klass)}
            if bad:
                raise ValueError(f"unknown keys in campaign section {name!r}: {sorted(bad)}")
            data[name] = klass(**section)
    if "preprocess" in data and not Path(data["preprocess"]).exists():
        candidate = REPOSITORY / data["preprocess"]
        if candidate.exists():
            data["preprocess"] = str(candidate)
    return CampaignConfig(**data)


def read_study_config(cls, path, output=None):
    """An instance of the study config dataclass ``cls`` (it has an ``output`` folder) from the
    YAML file ``path``, ``output`` replacing the file's; a key ``cls`` lacks, or a missing one,
    is refused naming the file."""
    raw = yaml.safe_load(Path(path).read_text()) or {}
    if output:
        raw["output"] = output
    try:
        cfg = cls(**raw)
    except TypeError as exc:
        raise ValueError(f"{path}: {exc}") from None
    cfg.output = Path(cfg.output)
    return cfg
