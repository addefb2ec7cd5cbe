"""Measuring the events step: flares through the full site pipeline and ``so-transients
events``, compared with the truth (``so-transients study events-check CONFIG``).

Two simulated datasets from one config: one with random flares (log-uniform peak flux and
rise time, a known spectral index), one noise-only (another seed). Each goes through the site
pipeline and the events command, and the results (``<output>/results``) say:

* ``events_per_flare``: for every flare with at least one detection, how many events match it
  (position within ``max_offset_arcmin``, detections within its active window): the target is
  exactly one for at least 95 % of them;
* ``lightcurve_recovery``: per rise-time bin, the eq. 1 fit against the truth (peak flux
  ratio, peak time offset, duration ratio) and the spectral index against the injected one;
* ``false_events``: events matching no flare, per wafer-hour (both bands of the wafer
  searched), with no band requirement, with detection in both bands, and with ``joint_snr``
  at least ``joint_snr_min``; with the efficiency (flares with a matching event) under each
  requirement.

``summary.md`` holds the three as Markdown (:func:`summary_markdown`, which also sets several
runs side by side).
"""
from __future__ import annotations

import copy
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from astropy.table import Table

from so_transients.common.angles import ARCMIN
from so_transients.common.bands import FLAVOR_BANDS
from so_transients.events.command import run_events
from so_transients.events.config import load_events_config
from so_transients.events.injections import match_events
from so_transients.common.robust import mad_std
from so_transients.sim.config import SimConfig
from so_transients.sim.simulate import simulate
from so_transients.site.pipeline import failed_groups, run_site_pipeline, write_site_config
from so_transients.campaign.config import read_study_config
from so_transients.campaign.provenance import stamp
from so_transients.campaign.full_check import site_processes

#: Rise-time bins (s) of the light-curve recovery table.
T_RISE_BINS = (0.5, 2.5, 15.0, 60.0, 301.0)


@dataclass
class EventsCheckConfig:
    output: Path
    simulation: dict
    seed: int = 2026
    nproc: int = 2
    preprocess: str = "configs/preprocess_paper.yaml"
    events: dict = field(default_factory=dict)     # sections of an events YAML
    max_offset_arcmin: float = 0.5
    window_pad_s: float = 5.0          # detections this long around the active window match
    joint_snr_min: float = 6.0

    @classmethod
    def read(cls, path, output=None):
        return read_study_config(cls, path, output)


def run_dataset(cfg: EventsCheckConfig, name, seed, flares: bool, progress=True):
    """Simulate, run the site pipeline and the events command; returns (dataset, events
    folder)."""
    sim = copy.deepcopy(cfg.simulation)
    if not flares:
        sim["flares"] = {"n": 0}
    folder = cfg.output / name
    result = simulate(SimConfig.from_dict({**sim, "seed": seed}), output=folder / "sim",
                      overwrite=True, progress=progress, workers=cfg.nproc)
    dataset = result.context.parent
    config = write_site_config(dataset, template=cfg.preprocess)
    run_site_pipeline(config, nproc=site_processes(cfg.nproc, 0), extra_args=["--overwrite"])
    errors = failed_groups(config)
    if errors:
        raise RuntimeError(f"events check {name}: the site pipeline failed:\n{errors}")
    events_yaml = folder / "events.yaml"
    events_yaml.write_text(yaml.safe_dump({"preprocess": str(config), "output": str(folder /
                                           "events"), "nproc": cfg.nproc, **cfg.events}))
    run_events(load_events_config(events_yaml), progress=progress)
    return dataset, folder / "events"


def requirement_masks(events: Table, joint_min) -> dict:
    bands = [set(str(b).split(",")) for b in events["bands"]]
    pairs = [set(p) for p in FLAVOR_BANDS.values()]
    return {"none": np.ones(len(events), bool),
            "both_bands": np.array([any(p <= b for p in pairs) for b in bands], bool),
            "joint_snr": np.nan_to_num(np.asarray(events["joint_snr"], float)) >= joint_min}


def events_per_flare(matches, flares: Table) -> Table:
    n = matches.sum(axis=0)
    seen = n > 0
    return Table(dict(flares_with_events=[int(seen.sum())],
                      exactly_one=[int((n[seen] == 1).sum())],
                      fraction_exactly_one=[float((n[seen] == 1).mean()) if seen.any()
                                            else np.nan],
                      max_events_per_flare=[int(n.max(initial=0))]))


def recovery_table(events, fits, flares, matches, peaks) -> Table:
    """Per rise-time bin: eq. 1 fits of the events matching exactly one flare, against it;
    ``peaks``: {(source_id, band): the flare's injected peak in that band}."""
    rows = []
    pairs = [(i, int(np.flatnonzero(matches[i])[0])) for i in range(len(events))
             if matches[i].sum() == 1]
    for lo, hi in zip(T_RISE_BINS[:-1], T_RISE_BINS[1:]):
        flux, dt, dur, alpha = [], [], [], []
        for i, j in pairs:
            fl = flares[j]
            if not lo <= fl["t_rise"] < hi:
                continue
            a = events["alpha_mf"][i]
            if np.isfinite(a):
                alpha.append(a - fl["spectral_index"])
            mine = fits[(fits["event_id"] == events["event_id"][i]) & fits["fit_ok"]]
            for fit in mine:
                s_true = peaks[(int(fl["source_id"]), str(fit["bandpass"]))]
                flux.append(fit["s_peak"] / s_true)
                dt.append(fit["t_peak"] - fl["t_peak"])
                dur.append((fit["t_rise"] + fit["t_decay"]) / (fl["t_rise"] + fl["t_decay"]))
        rows.append(dict(t_rise_lo=lo, t_rise_hi=hi, n_fits=len(flux),
                         s_peak_ratio=_median(flux), s_peak_scatter=_scatter(flux),
                         t_peak_offset=_median(dt), t_peak_scatter=_scatter(dt),
                         duration_ratio=_median(dur), duration_scatter=_scatter(dur),
                         n_alpha=len(alpha), alpha_bias=_median(alpha),
                         alpha_scatter=_scatter(alpha)))
    return Table(rows=rows)


def _median(values):
    return float(np.median(values)) if len(values) else np.nan


def _scatter(values):
    return float(mad_std(values)) if len(values) > 2 else np.nan


def false_event_table(flare_events, flare_matches, noise_events, flares, hours, joint_min):
    """Rates of events matching no flare (both datasets) and the efficiency, per
    requirement."""
    rows = []
    masks_f = requirement_masks(flare_events, joint_min)
    masks_n = requirement_masks(noise_events, joint_min)
    unmatched = ~flare_matches.any(axis=1)
    for name in masks_f:
        n_false = int((unmatched & masks_f[name]).sum() + masks_n[name].sum())
        found = (flare_matches & masks_f[name][:, None]).any(axis=0)
        rows.append(dict(requirement=name, false_events=n_false, wafer_hours=hours,
                         per_wafer_hour=n_false / hours,
                         per_wafer_hour_err=np.sqrt(max(n_false, 1)) / hours,
                         flares=len(flares), flares_found=int(found.sum()),
                         efficiency=float(found.mean()) if len(flares) else np.nan))
    return Table(rows=rows)


def run_events_check(cfg: EventsCheckConfig, progress=True, command="") -> Path:
    """Both datasets through the site pipeline and the events command, and the three result
    tables in ``<output>/results``, each naming ``command`` (what ran) and the commit."""
    flare_data, flare_out = run_dataset(cfg, "flares", cfg.seed, True, progress)
    noise_data, noise_out = run_dataset(cfg, "noise", cfg.seed + 1, False, progress)
    truth = Table.read(flare_data / "truth" / "flares.ecsv")
    flares = truth[truth["band"] == truth["band"][0]]       # one row per flare
    events = Table.read(flare_out / "events.ecsv")
    fits = Table.read(flare_out / "lightcurve_fits.ecsv")
    noise_events = Table.read(noise_out / "events.ecsv")
    matches = match_events(events, flares, cfg.max_offset_arcmin * ARCMIN, cfg.window_pad_s)
    sim = SimConfig.from_dict(cfg.simulation)
    n_wafers = len(sim.instrument.wafers or []) or 1
    # wafer-hours searched (both bands of each wafer) in the two datasets together
    hours = 2 * n_wafers * sim.observation.duration * sim.observation.n_obs / 3600.0
    results = cfg.output / "results"
    results.mkdir(parents=True, exist_ok=True)
    tables = dict(events_per_flare=events_per_flare(matches, flares),
                  lightcurve_recovery=recovery_table(
                      events, fits, flares, matches,
                      {(int(r["source_id"]), str(r["band"])): float(r["s_peak"]) for r in truth}),
                  false_events=false_event_table(events, matches, noise_events, flares, hours,
                                                 cfg.joint_snr_min))
    for name, table in tables.items():
        table.meta["comments"] = [command, f"{stamp()}; site config "
                                  f"{cfg.preprocess}, seeds {cfg.seed} (flares) and "
                                  f"{cfg.seed + 1} (noise)"]
        table.write(results / f"{name}.ecsv", overwrite=True)
    (results / "summary.md").write_text(summary_markdown({cfg.output.name: tables}))
    (results / "summary.json").write_text(json.dumps(
        {name: [dict(zip(table.colnames, row)) for row in table]
         for name, table in tables.items()}, indent=1,
        default=float))
    return results


#: The result tables of one events check, by file stem.
RESULT_TABLES = ("events_per_flare", "false_events", "lightcurve_recovery")


def read_results(folder) -> dict:
    """The result tables of an events check's ``results`` folder."""
    return {name: Table.read(Path(folder) / f"{name}.ecsv") for name in RESULT_TABLES}


def _median_scatter(median, scatter, fmt):
    if not np.isfinite(median):
        return "—"
    spread = fmt.replace("+", "").format(scatter) if np.isfinite(scatter) else None
    return fmt.format(median) + (f" ({spread})" if spread else "")


def summary_markdown(runs: dict) -> str:
    """Markdown tables of events checks, a row per run (``runs``: {name: read_results()}):
    association, false events per requirement and light-curve recovery per rise-time bin."""
    lines = ["| run | flares | with an event | exactly one event | most events for one flare |",
             "| --- | ---: | ---: | ---: | ---: |"]
    for name, t in runs.items():
        per = t["events_per_flare"][0]
        none = t["false_events"][t["false_events"]["requirement"] == "none"][0]
        lines.append(f"| {name} | {none['flares']} | {per['flares_with_events']} | "
                     f"{per['exactly_one']} | {per['max_events_per_flare']} |")
    lines += ["", "| run | requirement | false events | wafer-hours | per wafer-hour | "
              "flares with an event |", "| --- | --- | ---: | ---: | ---: | ---: |"]
    for name, t in runs.items():
        for r in t["false_events"]:
            lines.append(f"| {name} | {r['requirement']} | {r['false_events']} | "
                         f"{r['wafer_hours']:g} | {r['per_wafer_hour']:.1f} ± "
                         f"{r['per_wafer_hour_err']:.1f} | {r['flares_found']} |")
    lines += ["", "| run | t_r (s) | eq. 1 fits | peak flux / truth | peak time - truth (s) | "
              "duration / truth | spectral indices | index - injected |",
              "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name, t in runs.items():
        for r in t["lightcurve_recovery"]:
            lines.append(
                f"| {name} | {r['t_rise_lo']:g}-{r['t_rise_hi']:g} | {r['n_fits']} | "
                f"{_median_scatter(r['s_peak_ratio'], r['s_peak_scatter'], '{:.2f}')} | "
                f"{_median_scatter(r['t_peak_offset'], r['t_peak_scatter'], '{:+.1f}')} | "
                f"{_median_scatter(r['duration_ratio'], r['duration_scatter'], '{:.2f}')} | "
                f"{r['n_alpha']} | "
                f"{_median_scatter(r['alpha_bias'], r['alpha_scatter'], '{:+.2f}')} |")
    return "\n".join(lines) + "\n"
