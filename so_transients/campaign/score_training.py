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
                                           trains again without simulating); with
                                           ``open_cuts`` also ``..._open.ecsv``, the run
                                           with every cut open (``hand_cuts``: the cuts
                                           passed it in the configured run)
    work/<set>_seed<N>/                    the seed's simulation and archives, deleted once
                                           its candidates are written
    real_score.json                        the model (:mod:`so_transients.score.model`;
                                           ``real_score_open.json`` with ``open_cuts``)
    real_score.md                          the measured tables (``real_score_open.md``)

The model is trained on the ``train_seeds`` of both modes together and measured, per mode, on
``test_seeds`` (same scan) and ``scan_seeds`` (the ``test_scan`` pattern): the share of
artefacts rejected at the cut keeping 99 % and 99.9 % of the real candidates, and at the
99 % cut how many of the detections each kind would lose; for every fitted candidate, and for
the significant ones (``snr_fit >= 5``: the only ones a cut on the score changes, and where
a fluctuation of the noise no longer passes for a source by its S/N alone).
"""
from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import yaml
from astropy.table import Table, vstack
from tqdm.auto import tqdm

from so_transients.campaign.config import read_study_config
from so_transients.campaign.matching import group_crossings, match
from so_transients.campaign.provenance import commit, today
from so_transients.campaign.real_wafer import run_mode
from so_transients.common.angles import ARCMIN
from so_transients.common.bands import get_band
from so_transients.detect.error_scale import ErrorScale, median_scales
from so_transients.score.model import ScoreModel
from so_transients.score.person_labels import with_person_labels
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
    open_cuts: bool = False           # also run with transient_cuts open: train on every
    #                                   candidate, and compare the score with the cuts
    match_dt: float = 1.0
    match_offset_arcmin: float = 0.5
    loose_dt: float = 3.0
    loose_offset_arcmin: float = 3.0
    seed: int = 0                     # of the forest
    forest: dict = field(default_factory=lambda: {"n_trees": 100, "max_depth": 8,
                                                  "min_samples_leaf": 5})
    version: str = "1"
    labels: list = field(default_factory=list)   # vetting pages' label exports (CSV of
    #                                   `so-transients report`): a person's labels, trained
    #                                   on beside the simulated ones

    @classmethod
    def read(cls, path, output=None, labels=None):
        cfg = read_study_config(cls, path, output)
        cfg.labels = [*cfg.labels, *(labels or [])]
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


def label(candidates: Table, flares: Table, crossings: dict, cfg) -> tuple:
    """(label, source_id): 1 real, 0 artefact, -1 a flare fitted off its position (see the
    module doc), and the flare a real candidate is matched to (-1 for the others)."""
    tight = match(candidates, flares, crossings, cfg.match_dt, cfg.match_offset_arcmin * ARCMIN)
    loose = match(candidates, flares, crossings, cfg.loose_dt, cfg.loose_offset_arcmin * ARCMIN)
    source = np.asarray(tight["source_id"])
    out = np.where(np.asarray(loose["source_id"]) >= 0, -1, 0)
    out[source >= 0] = 1
    return out, source


def seed_sets(cfg) -> list:
    """(set name, seed, scan override or None) of every seed to simulate."""
    return ([("train", s, None) for s in cfg.train_seeds]
            + [("test", s, None) for s in cfg.test_seeds]
            + [("scan", s, cfg.test_scan) for s in cfg.scan_seeds])


def candidates_path(cfg, kind, seed, mode, variant="") -> Path:
    suffix = f"_{variant}" if variant else ""
    return cfg.output / "candidates" / f"{kind}_seed{seed}_{mode}{suffix}.ecsv"


def variants(cfg) -> list:
    """The runs of each mode: as configured (``""``) and, with ``open_cuts``, with every
    cut of ``transient_cuts`` open (``"open"``)."""
    return ["", "open"] if cfg.open_cuts else [""]


def open_cuts_template(template, error_scale, out) -> Path:
    """A copy of the site config ``template`` whose ``transient_cuts`` pass every candidate
    (each is then fitted) and whose ``transient_fit`` uses the fixed ``error_scale`` (one
    number, or an :class:`~so_transients.detect.error_scale.ErrorScale`) of the run with the
    cuts (whose null fits kept clear of only the candidates that passed them)."""
    cfg = yaml.safe_load(Path(template).read_text())
    for step in cfg["process_pipe"]:
        if step["name"] == "transient_cuts":
            step["calc"] = {**(step.get("calc") or {}), **OPEN_CUTS}
        if step["name"] == "transient_fit":
            step["calc"] = {**(step.get("calc") or {}),
                            "error_scale": ErrorScale.of(error_scale).as_list()}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return out


#: transient_cuts settings that pass every candidate
OPEN_CUTS = {"min_aspect_ratio": 1e-9, "time_tolerance": 1e9, "max_opposite_ratio": 1e9}


def _labelled(every, truth, crossings, cfg, mode, seed, kind, scan, n_flares):
    fitted = every[np.asarray(every["fit_ok"], bool)
                   & (np.nan_to_num(np.asarray(every["snr_fit"], float)) >= cfg.min_snr_fit)]
    fitted["label"], fitted["source_id"] = label(fitted, truth, crossings, cfg)
    fitted["mode"], fitted["seed"], fitted["set"] = mode, seed, kind
    fitted.meta = {"simulation": cfg.simulation, "seed": seed, "scan": scan or {},
                   "mode": mode, "n_flares": n_flares}
    return fitted


def make_candidates(cfg, kind, seed, scan, progress=True):
    """Simulate one seed, run each mode (and variant), write its labelled candidates (skipped
    when they exist)."""
    todo = [(m, v) for m in cfg.modes for v in variants(cfg)
            if not candidates_path(cfg, kind, seed, m, v).exists()]
    if not todo:
        return
    sim_cfg = yaml.safe_load((ROOT / cfg.simulation).read_text())   # an absolute path stays
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
    template = ROOT / cfg.preprocess
    for mode, variant in todo:
        path = candidates_path(cfg, kind, seed, mode, variant)
        if variant == "open":
            cut = Table.read(candidates_path(cfg, kind, seed, mode))
            scale = (median_scales(cut["error_scale"], cut["direction"]) if len(cut)
                     else None) or ErrorScale(1.0, 1.0)
            site = open_cuts_template(template, scale, work / "open_template.yaml")
            every = run_mode(sim, work / "runs_open", mode, cfg.max_far, template=site,
                             every=True)
        else:
            every = run_mode(sim, work / "runs", mode, cfg.max_far, template=template,
                             every=True)
        fitted = _labelled(every, truth, crossings, cfg, mode, seed, kind, scan, len(flares))
        if variant == "open":     # what the configured cuts decided of each candidate
            kept = set(zip(cut["obs_id"], cut["cand_id"])) if len(cut) else set()
            fitted["hand_cuts"] = [(o, c) in kept for o, c in zip(fitted["obs_id"],
                                                                 fitted["cand_id"])]
        path.parent.mkdir(parents=True, exist_ok=True)
        fitted.write(path.with_suffix(".tmp.ecsv"), overwrite=True)
        path.with_suffix(".tmp.ecsv").replace(path)
        if progress:
            n = np.bincount(np.asarray(fitted["label"]) + 1, minlength=3)
            tqdm.write(f"{kind} seed {seed} {mode}{' ' + variant if variant else ''}: "
                       f"{n[2]} real, {n[1]} artefact, {n[0]} off-position")
    shutil.rmtree(work, ignore_errors=True)   # the simulation and archives: tens of GB a set


def read_set(cfg, kind, variant="") -> Table:
    parts = [Table.read(candidates_path(cfg, k, s, m, variant)) for k, s, _ in seed_sets(cfg)
             if k == kind for m in cfg.modes]
    parts = [p for p in parts if len(p)]
    return vstack(parts, metadata_conflicts="silent") if parts else Table()


def measure(model: ScoreModel, table: Table, min_snr=5.0, recalls=(0.99, 0.999)) -> dict:
    """Per mode and population (``fitted``: every labelled candidate; ``significant``: those
    with ``snr_fit >= min_snr``, the ones a cut on the score can still change):
    :func:`~so_transients.score.training.rejection` of the model's scores, and at the 99 %
    cut of that population the detections (``detected``) of each label it keeps."""
    out = {}
    for mode in sorted(set(table["mode"])):
        t = table[(table["mode"] == mode) & (np.asarray(table["label"]) >= 0)]
        s = model.score(t)
        real = np.asarray(t["label"]) == 1
        det = np.asarray(t["detected"], bool)
        for name, sel in (("fitted", np.ones(len(t), bool)),
                          ("significant", np.asarray(t["snr_fit"], float) >= min_snr)):
            res = rejection(s[sel & real], s[sel & ~real], recalls)
            cut = threshold_at_recall(s[sel & real], recalls[0])
            res["detections"] = {"real": int((det & real).sum()),
                                 "real_kept": int((det & real & (s >= cut)).sum()),
                                 "artefact": int((det & ~real).sum()),
                                 "artefact_kept": int((det & ~real & (s >= cut)).sum())}
            out[f"{mode}/{name}"] = res
    return out


def _per_flare(values, source, how):
    """``how`` (np.max, np.any) of ``values`` over each flare's real candidates."""
    return np.array([how(values[source == f]) for f in np.unique(source)])


def against_cuts(model: ScoreModel, table: Table) -> dict:
    """Per mode, on the candidates of the runs with the cuts open: the configured cuts' share
    of flares kept (a flare is kept when one of its real candidates is) and of artefacts
    rejected (``hand_cuts``), and the share of artefacts the score rejects at the cut keeping
    as many flares, and at the cut keeping 99 % of them."""
    out = {}
    for mode in sorted(set(table["mode"])):
        t = table[(table["mode"] == mode) & (np.asarray(table["label"]) >= 0)]
        real = np.asarray(t["label"]) == 1
        if not real.any() or real.all():
            continue
        source = np.asarray(t["source_id"])[real]
        hand = np.asarray(t["hand_cuts"], bool)
        s = model.score(t)
        best = _per_flare(s[real], source, np.max)
        recall = float(_per_flare(hand[real], source, np.any).mean())
        same, at99 = threshold_at_recall(best, recall), threshold_at_recall(best, 0.99)
        out[mode] = {"n_flares": len(best), "n_real": int(real.sum()),
                     "n_false": int((~real).sum()), "cuts_recall": recall,
                     "cuts_rejected": float((~hand[~real]).mean()),
                     "score_rejected_same_recall": float((s[~real] < same).mean()),
                     "score_rejected_99": float((s[~real] < at99).mean()),
                     "score_recall_99": float((best >= at99).mean()), "cut_99": at99}
    return out


def train_and_measure(cfg) -> tuple[ScoreModel, dict]:
    """The model trained on the ``train`` seeds (every candidate of the runs with the cuts
    open, with ``open_cuts``; else those the cuts passed), and its figures on the held-out
    sets: ``test`` and ``scan`` (:func:`measure`, the candidates the cuts passed) and, with
    ``open_cuts``, ``test_open`` and ``scan_open`` (:func:`against_cuts`). The files of
    ``cfg.labels`` (a person's labels from vetting pages) are trained on too."""
    variant = "open" if cfg.open_cuts else ""
    train = with_person_labels(read_set(cfg, "train", variant), cfg.labels)
    use = np.asarray(train["label"]) >= 0
    settings = {k: v for k, v in asdict(cfg).items() if k != "output"}   # a local folder
    trained = {"config": getattr(cfg, "source", ""),
               "settings": json.loads(json.dumps(settings, default=str)),
               "commit": commit(), "date": today()}
    model = train_model(train[use], np.asarray(train["label"])[use], cfg.seed, cfg.version,
                        trained, **cfg.forest)
    figures = {kind: measure(model, read_set(cfg, kind)) for kind in ("test", "scan")}
    if cfg.open_cuts:
        figures.update({f"{kind}_open": against_cuts(model, read_set(cfg, kind, "open"))
                        for kind in ("test", "scan")})
    model.figures = figures
    return model, figures


def markdown(figures) -> str:
    names = {"test": "seeds", "scan": "seeds, other scan"}
    lines = ["| held out | mode | candidates | real | artefacts | rejected at 99 % recall "
             "(cut) | at 99.9 % | real detections kept | artefact detections kept |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for kind in ("test", "scan"):
        for key, r in figures.get(kind, {}).items():
            mode, population = key.split("/")
            a, b, d = r["0.99"], r["0.999"], r["detections"]
            lines.append(f"| {names[kind]} | {mode} | {population} | {a['n_real']} | "
                         f"{a['n_false']} | {a['rejected']:.3f} ({a['cut']:.3f}) | "
                         f"{b['rejected']:.3f} | {d['real_kept']} / {d['real']} | "
                         f"{d['artefact_kept']} / {d['artefact']} |")
    if any(k.endswith("_open") for k in figures):
        lines += ["", "| held out | mode | flares | artefacts | cuts: flares kept | cuts: "
                  "artefacts rejected | score: artefacts rejected at the cuts' flares | "
                  "score: flares kept, artefacts rejected at 99 % (cut) |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for kind in ("test", "scan"):
            for mode, r in figures.get(f"{kind}_open", {}).items():
                lines.append(f"| {names[kind]} | {mode} | {r['n_flares']} | {r['n_false']} | "
                             f"{r['cuts_recall']:.3f} | {r['cuts_rejected']:.3f} | "
                             f"{r['score_rejected_same_recall']:.3f} | "
                             f"{r['score_recall_99']:.3f}, {r['score_rejected_99']:.3f} "
                             f"({r['cut_99']:.3f}) |")
    return "\n".join(lines) + "\n"


def run_score_training(cfg: ScoreTrainingConfig, progress=True, model_out=None):
    """Every seed's candidates (made when missing), the model, its figures; returns the
    model's path."""
    sets = seed_sets(cfg)
    for kind, seed, scan in tqdm(sets, desc="seeds", disable=not progress):
        make_candidates(cfg, kind, seed, scan, progress)
    model, figures = train_and_measure(cfg)
    name = "real_score_open" if cfg.open_cuts else "real_score"
    path = model.save(model_out or cfg.output / f"{name}.json")
    (cfg.output / f"{name}.md").write_text(markdown(figures))
    return path, figures

