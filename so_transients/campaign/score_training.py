"""Candidates for the real-or-artefact score, labelled by the truth; the model trained on them
and measured on held-out seeds and a scan pattern it never saw (``so-transients study
train-score``).

Each seed simulates a real wafer (``simulation``: every imperfection of
``studies/configs/real_wafer.yaml`` at once: dead channels with jumps and cosmic rays, jumps,
cosmic rays hitting 5-40 detectors, NaN stretches, gain and noise scatter, time constants)
with ``n_flares`` flares of random peak flux and rise time, each peaking as it crosses a
random detector, and runs the site pipeline on it in each search mode
(:func:`so_transients.campaign.real_wafer.run_mode`). Every candidate ``transient_fit``
fitted with ``snr_fit >= min_snr_fit`` is kept, labelled

- 1 (``real``): an injected flare crossing explains it (within ``match_dt`` and
  ``match_offset_arcmin``, as the campaigns match);
- 0 (``artefact``): no flare comes within ``loose_dt`` and ``loose_offset_arcmin`` (noise,
  cosmic rays, jumps, what the imperfections leave);
- -1: a flare's crossing fitted off its position, left out of training and measurement.

``output/``::

    candidates/<set>_seed<N>_<mode>.ecsv   each seed's labelled candidates (kept: a rerun
                                           trains again without simulating)
    work/<set>_seed<N>/                    the seed's simulation and archives, deleted once
                                           its candidates are written
    real_score.json                        the model (:mod:`so_transients.score.model`)
    score.md                               the measured table

The model is trained on the ``train_seeds`` of both modes together and measured, per mode, on
``test_seeds`` (same scan) and ``scan_seeds`` (the ``test_scan`` pattern): the share of
artefacts rejected at the cut keeping 99 % and 99.9 % of the real candidates, and at the
99 % cut how many of the detections each kind would lose.
"""
from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import yaml
from astropy.table import Table, vstack
from tqdm.auto import tqdm

from so_transients.campaign.matching import group_crossings, match
from so_transients.campaign.real_wafer import run_mode
from so_transients.common.angles import ARCMIN
from so_transients.common.bands import get_band
from so_transients.score.model import ScoreModel
from so_transients.score.training import rejection, threshold_at_recall, train_model
from so_transients.sim.config import SimConfig
from so_transients.sim.focal_plane import tube_detectors
from so_transients.sim.simulate import simulate

ROOT = Path(__file__).resolve().parents[2]
LABELS = {1: "real", 0: "artefact", -1: "off-position flare"}


@dataclass
class ScoreTrainingConfig:
    output: Path
    simulation: str = "studies/configs/real_wafer.yaml"
    preprocess: str = "studies/configs/preprocess_paper_realistic.yaml"
    modes: list = field(default_factory=lambda: ["paper", "coherent"])
    max_far: float = 0.08             # coherent mode's cut (every candidate is kept anyway)
    duration: float = 600.0           # s per seed
    train_seeds: list = field(default_factory=lambda: [1, 2, 3, 4, 5, 6])
    test_seeds: list = field(default_factory=lambda: [101, 102])
    scan_seeds: list = field(default_factory=lambda: [201, 202])
    test_scan: dict = field(default_factory=lambda: {"el": 40.0, "sky_speed": 0.7,
                                                     "sweep_time": 60.0})
    n_flares: int = 25
    s_peak_mjy: list = field(default_factory=lambda: [150.0, 3000.0])   # log-uniform
    t_rise: list = field(default_factory=lambda: [0.5, 1.0, 2.5, 5.0, 10.0, 30.0])
    min_snr_fit: float = 3.0
    match_dt: float = 1.0
    match_offset_arcmin: float = 0.5
    loose_dt: float = 3.0
    loose_offset_arcmin: float = 3.0
    seed: int = 0                     # of the forest
    forest: dict = field(default_factory=lambda: {"n_trees": 100, "max_depth": 8,
                                                  "min_samples_leaf": 5})
    version: str = "1"

    @classmethod
    def read(cls, path, output=None):
        raw = yaml.safe_load(Path(path).read_text()) or {}
        if output:
            raw["output"] = output
        try:
            cfg = cls(**raw)
        except TypeError as exc:
            raise ValueError(f"{path}: {exc}") from None
        cfg.output = Path(cfg.output)
        cfg.source = str(path)
        return cfg


def flare_list(seed, duration, n, s_peak_mjy, t_rise, wafer="w16", band="f090"):
    """``n`` flares of log-uniform peak flux and random rise time, each peaking as it crosses
    a random detector of ``wafer`` ``band``, at least 20 s apart."""
    rng = np.random.default_rng(5000 + seed)
    dets = tube_detectors("i1")
    names = [d for d, w, b in zip(dets["det_id"], dets["wafer_slot"], dets["bandpass"])
             if w == wafer and b == band]
    slots = np.arange(20.0, duration - 20.0, 20.0)
    n = min(n, len(slots))
    times = np.sort(rng.choice(slots, n, replace=False) + rng.uniform(0, 5, n))
    fluxes = np.exp(rng.uniform(*np.log(s_peak_mjy), n))
    rises = rng.choice(t_rise, n)
    return [{"at_detector": str(d), "at_time": float(t), "t_peak": float(t),
             "s_peak_mjy": float(s), "t_rise": float(r)}
            for d, t, s, r in zip(rng.choice(names, n, replace=False), times, fluxes, rises)]


def label(candidates: Table, flares: Table, crossings: dict, cfg) -> np.ndarray:
    """1 real, 0 artefact, -1 a flare fitted off its position (see the module doc)."""
    tight = match(candidates, flares, crossings, cfg.match_dt, cfg.match_offset_arcmin * ARCMIN)
    loose = match(candidates, flares, crossings, cfg.loose_dt, cfg.loose_offset_arcmin * ARCMIN)
    out = np.where(np.asarray(loose["source_id"]) >= 0, -1, 0)
    out[np.asarray(tight["source_id"]) >= 0] = 1
    return out


def seed_sets(cfg) -> list:
    """(set name, seed, scan override or None) of every seed to simulate."""
    return ([("train", s, None) for s in cfg.train_seeds]
            + [("test", s, None) for s in cfg.test_seeds]
            + [("scan", s, cfg.test_scan) for s in cfg.scan_seeds])


def candidates_path(cfg, kind, seed, mode) -> Path:
    return cfg.output / "candidates" / f"{kind}_seed{seed}_{mode}.ecsv"


def make_candidates(cfg, kind, seed, scan, progress=True):
    """Simulate one seed, run each mode, write its labelled candidates (skipped when they
    exist)."""
    todo = [m for m in cfg.modes if not candidates_path(cfg, kind, seed, m).exists()]
    if not todo:
        return
    sim_cfg = yaml.safe_load((ROOT / cfg.simulation).read_text()
                             if not Path(cfg.simulation).is_absolute()
                             else Path(cfg.simulation).read_text())
    sim_cfg["observation"]["duration"] = cfg.duration
    if scan:
        sim_cfg["scan"] = {**sim_cfg.get("scan", {}), **scan}
    flares = flare_list(seed, cfg.duration, cfg.n_flares, cfg.s_peak_mjy, cfg.t_rise)
    work = cfg.output / "work" / f"{kind}_seed{seed}"
    sim_cfg.update(seed=seed, output=str(work / "sim"), flares={"list": flares})
    sim = simulate(SimConfig.from_dict(sim_cfg), overwrite=True, progress=False)
    truth = Table.read(sim.context.parent / "truth" / "flares.ecsv")
    crossings = group_crossings(sim.context, truth,
                                {b: get_band(b).fwhm for b in set(truth["band"])})
    template = Path(cfg.preprocess)
    template = template if template.is_absolute() else ROOT / template
    for mode in todo:
        every = run_mode(sim, work / "runs", mode, cfg.max_far, template=template, every=True)
        fitted = every[np.asarray(every["fit_ok"], bool)
                       & (np.nan_to_num(np.asarray(every["snr_fit"], float)) >= cfg.min_snr_fit)]
        fitted["label"] = label(fitted, truth, crossings, cfg)
        fitted["mode"], fitted["seed"], fitted["set"] = mode, seed, kind
        fitted.meta = {"simulation": cfg.simulation, "seed": seed, "scan": scan or {},
                       "mode": mode, "n_flares": len(flares)}
        path = candidates_path(cfg, kind, seed, mode)
        path.parent.mkdir(parents=True, exist_ok=True)
        fitted.write(path.with_suffix(".tmp.ecsv"), overwrite=True)
        path.with_suffix(".tmp.ecsv").replace(path)
        if progress:
            n = np.bincount(np.asarray(fitted["label"]) + 1, minlength=3)
            tqdm.write(f"{kind} seed {seed} {mode}: {n[2]} real, {n[1]} artefact, "
                       f"{n[0]} off-position")
    shutil.rmtree(work, ignore_errors=True)   # the simulation and archives: tens of GB a set


def read_set(cfg, kind) -> Table:
    parts = [Table.read(candidates_path(cfg, k, s, m)) for k, s, _ in seed_sets(cfg)
             if k == kind for m in cfg.modes]
    parts = [p for p in parts if len(p)]
    return vstack(parts, metadata_conflicts="silent") if parts else Table()


def measure(model: ScoreModel, table: Table, recalls=(0.99, 0.999)) -> dict:
    """Per mode: :func:`~so_transients.score.training.rejection` of the model's scores, and at
    the 99 % cut the detections (``detected``) of each label it keeps."""
    out = {}
    for mode in sorted(set(table["mode"])):
        t = table[(table["mode"] == mode) & (np.asarray(table["label"]) >= 0)]
        s = model.score(t)
        real = np.asarray(t["label"]) == 1
        res = rejection(s[real], s[~real], recalls)
        cut = threshold_at_recall(s[real], recalls[0])
        det = np.asarray(t["detected"], bool)
        res["detections"] = {"real": int((det & real).sum()),
                             "real_kept": int((det & real & (s >= cut)).sum()),
                             "artefact": int((det & ~real).sum()),
                             "artefact_kept": int((det & ~real & (s >= cut)).sum())}
        out[mode] = res
    return out


def _commit():
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                              capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def train_and_measure(cfg) -> tuple[ScoreModel, dict]:
    train = read_set(cfg, "train")
    use = np.asarray(train["label"]) >= 0
    trained = {"config": getattr(cfg, "source", ""), "settings": json.loads(json.dumps(
                   asdict(cfg), default=str)),
               "commit": _commit(), "date": datetime.now(timezone.utc).strftime("%Y-%m-%d")}
    model = train_model(train[use], np.asarray(train["label"])[use], cfg.seed, cfg.version,
                        trained, **cfg.forest)
    figures = {kind: measure(model, read_set(cfg, kind)) for kind in ("test", "scan")}
    model.figures = figures
    return model, figures


def markdown(figures) -> str:
    lines = ["| held out | mode | real | artefacts | rejected at 99 % recall | at 99.9 % | "
             "real detections kept | artefact detections kept |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    names = {"test": "seeds", "scan": "seeds, other scan"}
    for kind, per_mode in figures.items():
        for mode, r in per_mode.items():
            a, b, d = r["0.99"], r["0.999"], r["detections"]
            lines.append(f"| {names[kind]} | {mode} | {a['n_real']} | {a['n_false']} | "
                         f"{a['rejected']:.3f} (cut {a['cut']:.3f}) | {b['rejected']:.3f} | "
                         f"{d['real_kept']} / {d['real']} | {d['artefact_kept']} / "
                         f"{d['artefact']} |")
    return "\n".join(lines) + "\n"


def run_score_training(cfg: ScoreTrainingConfig, progress=True, model_out=None):
    """Every seed's candidates (made when missing), the model, its figures; returns the
    model's path."""
    sets = seed_sets(cfg)
    for kind, seed, scan in tqdm(sets, desc="seeds", disable=not progress):
        make_candidates(cfg, kind, seed, scan, progress)
    model, figures = train_and_measure(cfg)
    path = model.save(model_out or cfg.output / "real_score.json")
    (cfg.output / "score.md").write_text(markdown(figures))
    return path, figures

