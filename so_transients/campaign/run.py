"""Running a campaign end to end: noise-only groups, work units, results; resumable.

``<output>/`` holds::

    campaign.json        the config and its digest; a different config is refused
    noise/sim/<g>/       the noise-only dataset of each group (a sotodlib context), deleted
                         once the group is prepared
    noise/groups/<g>/    each prepared group (see :mod:`so_transients.campaign.noise`) and,
                         with a false-alarm budget, its background (:mod:`.far_budget`)
    units/               one pair of ECSV files per (cell, observation) work unit
    results/             the tables, Markdown and figures (:mod:`.report`, :mod:`.figures`)

An interrupted campaign is continued by running the same command again: prepared groups and
finished units are kept, the rest is done. Units are dispatched through sotodlib's executor
(``sotodlib.utils.procs_pool.get_exec_env``): a process pool here, ``mpi4py.futures`` under
``mpirun`` (rank 0 runs this module, the other ranks serve as workers).
"""
from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from pathlib import Path

from astropy.table import Table, vstack
from tqdm.auto import tqdm

from so_transients.common.parallel import executor, run_all
from so_transients.campaign.config import CampaignConfig, Cell
from so_transients.campaign.far_budget import background_done, search_background
from so_transients.campaign.full_check import run_full_check
from so_transients.campaign.noise import (
    PREPARED_FORMAT, campaign_groups, false_positives_done, prepare_group, search_false_positives,
    simulate_group
)
from so_transients.campaign.report import write_results
from so_transients.campaign.work_units import run_unit, unit_done, unit_paths

log = logging.getLogger(__name__)


def check_state(cfg: CampaignConfig, out: Path, restart=False):
    """Refuse to mix configs: ``out`` must be new, hold this config, or be restarted."""
    state = out / "campaign.json"
    digest = cfg.digest()
    if state.exists():
        held = json.loads(state.read_text()).get("digest")
        if held != digest:
            if not restart:
                raise ValueError(f"{out} holds a campaign with another config (digest {held}, "
                                 f"this one {digest}); use another output or --restart")
            for sub in ("units", "results"):
                shutil.rmtree(out / sub, ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    state.write_text(json.dumps({"digest": digest, "config": dataclasses.asdict(cfg)}, indent=1,
                                default=str))


def prepare_noise(cfg, out: Path, progress=True, pool=None):
    """Simulate and prepare every noise-only group that is missing; returns
    ``({Group: folder}, futures)``.

    Groups are preprocessed and filtered here one at a time (each holds a whole wafer-band
    hour in memory). With a ``pool`` the groups' simulations are submitted there first, so
    the next group is being simulated while this one is preprocessed (mostly single-threaded),
    and so is the false-positive search of a prepared group, which only reads its files, and
    with a false-alarm budget its background (:mod:`.far_budget`); ``futures`` are those
    searches (empty without a pool: they ran here).
    """
    standard, search = cfg.pipeline_steps()
    for step in standard:   # filter threads: as many as the campaign's processes
        if step["name"] == "transient_filter":
            step.setdefault("process", {}).setdefault("workers", cfg.nproc)
    stamp = cfg.noise_digest()
    settings = dataclasses.asdict(cfg.significance_settings())
    background = f"{stamp} {json.dumps(settings, sort_keys=True)}"
    budget = cfg.far_statistic() is not None
    groups = campaign_groups(cfg)
    folders = {g: out / "noise" / "groups" / g.label for g in groups}
    sims = NoiseSimulations(cfg, out, [g for g in groups if not _prepared(folders[g], stamp)],
                            pool)
    futures = []
    for group in tqdm(groups, desc="noise-only groups", disable=not progress):
        folder = folders[group]
        if group in sims:
            (folder / "digest.txt").unlink(missing_ok=True)
            prepare_group(sims.context(group), group, standard, search, folder)
            (folder / "digest.txt").write_text(stamp)
            sims.discard(group)
        jobs = []
        if not false_positives_done(folder, cfg.inverted, stamp):
            jobs.append((search_false_positives, group, str(folder), search, cfg.inverted,
                         stamp))
        if budget and not background_done(folder, background):
            jobs.append((search_background, group, str(folder), search, settings, background))
        for job, *args in jobs:
            if pool is None:
                job(*args)
            else:
                futures.append(pool.submit(job, *args))
    return folders, futures


def _prepared(folder: Path, stamp) -> bool:
    digest = folder / "digest.txt"
    info = folder / "info.json"
    return (info.exists() and digest.exists() and digest.read_text() == stamp
            and json.loads(info.read_text()).get("format") == PREPARED_FORMAT)


class NoiseSimulations:
    """The noise-only TODs of ``groups``, simulated in order, each in ``pool`` (when given)
    while the previous group is being prepared, at most ``cfg.nproc`` ahead: a group's TOD
    (2.6 GB per wafer-band-hour at MF, 4 GB at UHF) is deleted by :meth:`discard` once its
    group is prepared, so the disk holds only those in flight."""

    def __init__(self, cfg, out: Path, groups, pool=None):
        self.cfg, self.out, self.pool = cfg, out, pool
        self.order = list(groups)
        self.futures = {}

    def __contains__(self, group):
        return group in self.order

    def _args(self, group):
        return (self.cfg.sim, self.folder(group), group, self.cfg.sim_digest())

    def folder(self, group) -> Path:
        return self.out / "noise" / "sim" / group.label

    def context(self, group) -> str:
        """The group's context.yaml, once simulated; the next groups are submitted now."""
        if self.pool is None:
            return simulate_group(*self._args(group))
        k = self.order.index(group)
        for ahead in self.order[k:k + 1 + max(self.cfg.nproc, 1)]:
            if ahead not in self.futures:
                self.futures[ahead] = self.pool.submit(simulate_group, *self._args(ahead))
        return self.futures.pop(group).result()

    def discard(self, group):
        """Delete the group's simulated TOD (its prepared folder holds all a campaign needs;
        preprocessing it again simulates it again)."""
        shutil.rmtree(self.folder(group), ignore_errors=True)


def split_flares(n, n_obs):
    """Flares per observation: ``n`` shared as evenly as possible."""
    return [n // n_obs + (k < n % n_obs) for k in range(n_obs)]


def unit_specs(cfg, out: Path, folders: dict) -> list:
    """Every (cell, observation) work unit, as plain dicts."""
    _, search = cfg.pipeline_steps()
    digest = cfg.digest()
    specs = []
    for cell in cfg.cells:
        # the observations holding this band (each tube has its own obs_id)
        obs_ids = sorted({g.obs_id for g in folders if g.band == cell.band})
        first = 0
        for obs_id, n in zip(obs_ids, split_flares(cfg.n_flares, len(obs_ids))):
            groups = [((g.obs_id, g.wafer, g.band), str(f)) for g, f in folders.items()
                      if g.obs_id == obs_id and g.band == cell.band]
            if n and groups:
                specs.append(dict(cell=dataclasses.asdict(cell), obs_id=obs_id, n=n,
                                  first_id=first, groups=groups, search_steps=search,
                                  injection=dataclasses.asdict(cfg.injection),
                                  max_dt=cfg.matching.max_dt,
                                  max_offset_arcmin=cfg.matching.max_offset_arcmin,
                                  seed=cfg.seed, digest=digest, output=str(out)))
            first += n
    return specs


def run_units(specs, progress=True, pool=None, as_completed=None):
    """Run the work units, in ``pool`` if given (else here, one after the other); returns
    their summaries."""
    return run_all(run_unit, specs, "injections", progress, pool, as_completed)


def collect(specs):
    """(flares, detections) of the work units ``specs`` (all finished)."""
    flares, detections = [], []
    for spec in specs:
        flares_path, det_path = unit_paths(spec["output"], _cell(spec), spec["obs_id"])
        flares.append(Table.read(flares_path))
        det = Table.read(det_path)
        if len(det):
            detections.append(det)
    for table in flares + detections:
        table.meta.clear()
    return (vstack(flares) if flares else Table()), (vstack(detections) if detections else Table())


def run_campaign(cfg: CampaignConfig, restart=False, progress=True, pool=None,
                 as_completed=None, command="") -> Path:
    """Run (or continue) ``cfg``; returns the results folder, whose tables name ``command``
    (what ran), the site config and the commit."""
    out = Path(cfg.output)
    check_state(cfg, out, restart)
    own = pool is None and cfg.nproc > 1
    if own:
        pool, as_completed = executor(cfg.nproc)
    try:
        folders, searches = prepare_noise(cfg, out, progress, pool)
        specs = unit_specs(cfg, out, folders)
        todo = [s for s in specs if not unit_done(out, _cell(s), s["obs_id"], s["digest"])]
        # slowest first (slow, bright flares are crossed most often): no process idles at the end
        todo.sort(key=lambda s: (s["cell"]["t_rise"], s["cell"]["s_peak"]), reverse=True)
        if todo:
            run_units(todo, progress, pool, as_completed)
        for search in searches:
            search.result()
    finally:
        if own and pool is not None:
            pool.shutdown()
    flares, detections = collect(specs)
    check = None
    if cfg.full_check.cells:
        check = run_full_check(cfg, out, folders, progress)
    return write_results(cfg, out / "results", flares, detections, folders, check, command)


def _cell(spec):
    return Cell(**spec["cell"])
