"""Simulate SO LAT observations into a sotodlib dataset, one wafer-band group at a time.

For every time block (``observation.n_obs`` of them) and every simulated tube, one observation
is written. Within it each detset (wafer x band) is generated in chunks of detectors: white
noise, the shared atmosphere screen, the CMB, flares, steady and moving sources, glitches and the
instrument's imperfections (:mod:`so_transients.sim.imperfections`, :mod:`so_transients.sim.jumps`)
are added to a chunk and written to disk before the next chunk starts, so memory stays far below
the size of one wafer-band's TOD.

Reproducibility: every random draw comes from a generator seeded by ``(seed, component, ...)``
with stable integer keys (block index, CRC32 of detector or wafer names), so the same seed gives
bit-identical files whatever the chunking or the order of generation.
"""
from __future__ import annotations

import shutil
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy.table import Table, vstack
from tqdm.auto import tqdm

from so_transients.common.bands import FLAVOR_SAMPLE_RATE, get_band
from so_transients.io.tod_file import TodWriter
from so_transients.common.pointing import boresight_sightline, horizon_offsets, radec_of_samples
from so_transients.sim import atmosphere, focal_plane
from so_transients.sim.cmb import CmbSky, footprint_geometry
from so_transients.sim.config import SimConfig
from so_transients.sim.dataset import DatasetWriter, obs_id_for
from so_transients.sim.glitches import add_glitches, draw_glitches
from so_transients.sim.imperfections import (
    DetectorFlaws, draw_flaws, flaws_table, metadata_positions, one_over_f, respond_to_sky,
    silence_dead
)
from so_transients.sim.gaps import add_gaps, draw_gaps
from so_transients.sim.jumps import add_jumps, draw_jumps
from so_transients.sim.moving import (
    MOVING_COLUMNS, draw_moving_sources, moving_crossings, track_table
)
from so_transients.sim.scan import boresight, constant_velocity_mask
from so_transients.sim.sources import (
    BEAM_REACH_SIGMA, FLARE_COLUMNS, POINT_SOURCE_COLUMNS, PointingContext, add_sources,
    draw_flares, draw_point_sources, empty_table, source_crossings
)

DETS_PER_CHUNK = 32
# component keys of the random streams
WHITE, ATMOSPHERE, CMB, FLARES, POINT_SOURCES, GLITCHES, FLAWS, ONE_OVER_F, JUMPS = range(1, 10)
DEAD_NOISE, GAPS = 10, 11


def rng_for(seed: int, *keys) -> np.random.Generator:
    """Generator for one random stream; string keys are hashed with CRC32 (stable)."""
    ints = [zlib.crc32(k.encode()) if isinstance(k, str) else int(k) for k in keys]
    return np.random.default_rng([int(seed), *ints])


@dataclass
class SimulationResult:
    """What :func:`simulate` produced."""

    context: Path
    obs_ids: list
    flares: Table
    point_sources: Table
    glitches: Table
    detsets: dict = field(default_factory=dict)   # obs_id -> [detset, ...]
    moving_sources: Table = field(default_factory=Table)
    jumps: Table = field(default_factory=Table)
    gaps: Table = field(default_factory=Table)      # NaN stretches (sim.gaps)
    detectors: Table = field(default_factory=Table)   # the imperfections of every detector


@dataclass
class _Sources:
    """Truth tables of everything on the sky: flares, steady and moving sources."""

    flares: Table
    point_sources: Table
    moving: Table

    def band(self, name) -> "_Sources":
        return _Sources(*(t[t["band"] == name] for t in (self.flares, self.point_sources,
                                                       self.moving)))


@dataclass
class Timeline:
    """Timestamps and boresight of one tube flavour during one time block."""

    timestamps: np.ndarray
    t_rel: np.ndarray
    az: np.ndarray
    el: np.ndarray
    sight: object            # so3g CelestialSightLine of the boresight
    sample_rate: float

    @property
    def bore_q(self) -> np.ndarray:
        return np.asarray(self.sight.Q)


def _timeline(start, duration, sample_rate, pattern) -> Timeline:
    n = int(round(duration * sample_rate))
    t_rel = np.arange(n) / sample_rate
    az, el, _ = boresight(t_rel, pattern)
    t = start + t_rel
    return Timeline(t, t_rel, az, el, boresight_sightline(t, az, el, np.zeros(n)), sample_rate)


def _selected_dets(config: SimConfig, tube):
    dets = focal_plane.tube_detectors(tube)
    keep = np.ones(len(dets["xi"]), bool)
    if config.instrument.wafers is not None:
        keep &= np.isin(dets["wafer_slot"], config.instrument.wafers)
    if config.instrument.bands is not None:
        keep &= np.isin(dets["bandpass"], config.instrument.bands)
    return {k: v[keep] for k, v in dets.items()}


def _validate_instrument(config: SimConfig):
    for tube in config.instrument.tubes:
        focal_plane.tube_flavor(tube)   # raises on unknown tubes
    dets = {t: _selected_dets(config, t) for t in config.instrument.tubes}
    empty = [t for t, d in dets.items() if len(d["xi"]) == 0]
    if empty:
        raise ValueError(f"no detectors selected in tubes {empty}: check instrument.wafers "
                         f"and instrument.bands")
    return dets


class _BlockSky:
    """Sky and atmosphere shared by every tube during one time block."""

    def __init__(self, config: SimConfig, block: int, ref: Timeline, all_dets):
        self.config = config
        self.atm = None
        self._unit_psd = {}
        if config.atmosphere.enabled:
            el_offsets = np.concatenate([d["eta"] for d in all_dets.values()])
            pad = np.abs(el_offsets).max() + 0.01
            bounds = atmosphere.screen_bounds(config.atmosphere, ref.t_rel, ref.az,
                                              ref.el[0] - pad, ref.el[0] + pad)
            self.atm = atmosphere.AtmosphereScreen(config.atmosphere, bounds,
                                                   rng_for(config.seed, ATMOSPHERE, block))
        self.cmb = None
        if config.cmb.enabled:
            step = max(1, len(ref.timestamps) // 20000)
            ra, dec = radec_of_samples(ref.bore_q, [0.0], [0.0],
                                       np.zeros(len(ref.timestamps[::step]), int),
                                       np.arange(0, len(ref.timestamps), step))
            shape, wcs = footprint_geometry(ra, dec, np.radians(3.0),
                                            np.radians(config.cmb.resolution_arcmin / 60))
            self.cmb = CmbSky(shape, wcs, rng_for(config.seed, CMB, block))

    def atmosphere_scale(self, band, white_mjy, tl: Timeline):
        fknee = self.config.atmosphere.fknee[band.name]
        key = (fknee, tl.sample_rate)
        if key not in self._unit_psd:
            self._unit_psd[key] = atmosphere.unit_psd_at(self.atm, tl.t_rel, tl.az, tl.el[0],
                                                         tl.sample_rate, fknee)
        return atmosphere.band_amplitude(self._unit_psd[key], white_mjy, tl.sample_rate)


def _draw_sources(config: SimConfig, blocks, all_dets):
    """Flares, point sources and moving sources of the whole dataset, drawn block by block."""
    bands = sorted({b for d in all_dets.values() for b in d["bandpass"]})
    det_cat = {k: np.concatenate([d[k] for d in all_dets.values()])
               for k in ("xi", "eta", "det_id")}
    wafers = {w for d in all_dets.values() for w in d["wafer_slot"]}
    pitch = min(focal_plane.pixel_pitch(w) for w in wafers)
    flare_rng = rng_for(config.seed, FLARES)
    n_per_block = np.bincount(flare_rng.integers(len(blocks), size=config.flares.n),
                              minlength=len(blocks))
    ps_rng = rng_for(config.seed, POINT_SOURCES)
    flares, sources, moving = [], [], empty_table(MOVING_COLUMNS)
    first_start = blocks[0][1].timestamps[0]
    for b, (_, ref) in enumerate(blocks):
        ctx = PointingContext(ref.timestamps, ref.bore_q, constant_velocity_mask(ref.t_rel,
                              config.scan), det_cat["xi"], det_cat["eta"], det_cat["det_id"], pitch)
        offset = ref.timestamps[0] - first_start
        listed = [dict(e, t_peak=e["t_peak"] - offset,
                       **({"at_time": e["at_time"] - offset} if "at_time" in e else {}))
                  for e in config.flares.list
                  if 0 <= e["t_peak"] - offset <= ref.t_rel[-1]]
        block_cfg = type(config.flares)(**{**config.flares.__dict__, "n": int(n_per_block[b]),
                                           "list": listed})
        flares.append(draw_flares(block_cfg, bands, ctx, flare_rng))
        if b == 0:
            sources.append(draw_point_sources(config.point_sources, bands, ctx, ps_rng))
            moving = draw_moving_sources(config.moving_sources, bands, ctx)
    flares = vstack(flares) if flares else empty_table(FLARE_COLUMNS)
    if len(flares):   # renumber across blocks: one id per physical flare
        _, flares["source_id"] = np.unique(np.stack([flares["t_peak"], flares["ra"]]), axis=1,
                                           return_inverse=True)
        flares.sort(["source_id", "band"])
    return _Sources(flares, vstack(sources) if sources else empty_table(POINT_SOURCE_COLUMNS),
                    moving)


def planned_detsets(config: SimConfig) -> dict:
    """``{obs_id: [detset, ...]}``: every observation and detset (``<wafer>_<band>``) that
    ``config`` simulates."""
    all_dets = _validate_instrument(config)
    obs = config.observation
    plan = {}
    for k in range(obs.n_obs):
        for tube in config.instrument.tubes:
            dets = all_dets[tube]
            plan[obs_id_for(obs.start + k * (obs.duration + obs.gap), tube)] = sorted(
                {f"{w}_{b}" for w, b in zip(dets["wafer_slot"], dets["bandpass"])})
    return plan


def _wanted_detsets(config, detsets):
    """``{obs_id: [detset, ...]}`` to write: all of :func:`planned_detsets`, or those in
    ``detsets`` (each of which must be planned)."""
    plan = planned_detsets(config)
    if detsets is None:
        return plan
    wanted, planned = set(detsets), {d for ds in plan.values() for d in ds}
    if wanted - planned:
        raise ValueError(f"detsets {sorted(wanted - planned)} are not simulated by this config "
                         f"(it has {sorted(planned)})")
    return {o: [d for d in ds if d in wanted] for o, ds in plan.items()}


def simulate(config: SimConfig, output=None, overwrite=False, progress=True,
             workers=1, detsets=None) -> SimulationResult:
    """Run the simulation described by ``config`` and write the dataset to ``output``;
    ``workers`` threads generate chunks of detectors (the result does not depend on it).

    ``detsets``: write only these detsets (``<wafer>_<band>``, in every observation that has
    them). The sky, the sources, the glitches and every detector's noise are drawn as in the
    full simulation, so each detset's data are identical to the full simulation's.
    """
    root = Path(output or config.output)
    if (root / "context.yaml").exists():
        if not overwrite:
            raise FileExistsError(f"{root} already holds a dataset; pass overwrite=True "
                                  "(--overwrite) to replace it")
        shutil.rmtree(root)
    all_dets = _validate_instrument(config)
    flavors = {t: focal_plane.tube_flavor(t) for t in config.instrument.tubes}
    obs_cfg = config.observation
    starts = [obs_cfg.start + k * (obs_cfg.duration + obs_cfg.gap) for k in range(obs_cfg.n_obs)]
    ref_flavor = flavors[config.instrument.tubes[0]]
    blocks = [(s, _timeline(s, obs_cfg.duration, FLAVOR_SAMPLE_RATE[ref_flavor], config.scan))
              for s in starts]
    sources = _draw_sources(config, blocks, all_dets)
    flaws = {t: draw_flaws(config, t, all_dets[t],
                           lambda *keys: rng_for(config.seed, FLAWS, *keys))
             for t in config.instrument.tubes}

    writer = DatasetWriter(root)
    result = SimulationResult(root / "context.yaml", [], sources.flares, sources.point_sources,
                              Table(), moving_sources=sources.moving)
    truth = {"glitches": [], "jumps": [], "gaps": []}
    wanted = _wanted_detsets(config, detsets)
    for b, (start, ref) in enumerate(blocks):
        sky = _BlockSky(config, b, ref, all_dets)
        for tube in config.instrument.tubes:
            obs_id = obs_id_for(start, tube)
            if not wanted[obs_id]:
                continue
            tl = ref if flavors[tube] == ref_flavor else _timeline(
                start, obs_cfg.duration, FLAVOR_SAMPLE_RATE[flavors[tube]], config.scan)
            _simulate_obs(config, writer, sky, tl, tube, obs_id, b, all_dets[tube], flaws[tube],
                          sources, progress, workers, wanted[obs_id], truth)
            result.obs_ids.append(obs_id)
    result.glitches = vstack(truth["glitches"]) if truth["glitches"] else Table()
    if config.jumps.enabled and truth["jumps"]:
        result.jumps = vstack(truth["jumps"])
    if config.gaps.rate_per_hour > 0 and truth["gaps"]:
        result.gaps = vstack(truth["gaps"])
    if any(not f.ideal for f in flaws.values()):
        result.detectors = vstack([flaws_table(all_dets[t], f) for t, f in flaws.items()])
    _write_truth(root, result, (blocks[0][1].timestamps[0], blocks[-1][1].timestamps[-1]))
    writer.finish(config.to_dict())
    result.detsets = {o: wanted[o] for o in result.obs_ids}
    return result


def _write_truth(root, result: SimulationResult, span):
    """Truth tables of ``result``; those of options that are off are not written.
    ``span``: first and last ctime of the dataset (for the moving sources' tracks)."""
    result.flares.write(root / "truth/flares.ecsv", overwrite=True)
    result.point_sources.write(root / "truth/point_sources.ecsv", overwrite=True)
    for name in ("glitches", "jumps", "gaps", "detectors"):
        table = getattr(result, name)
        if len(table.colnames):
            table.write(root / f"truth/{name}.ecsv", overwrite=True)
    if len(result.moving_sources):
        result.moving_sources.write(root / "truth/moving_sources.ecsv", overwrite=True)
        track_table(result.moving_sources, *span).write(root / "truth/moving_source_tracks.ecsv",
                                                        overwrite=True)


def _simulate_obs(config, writer, sky, tl: Timeline, tube, obs_id, block, dets,
                  flaws: DetectorFlaws, sources: _Sources, progress, workers, detsets, truth):
    """Write one observation (``detsets`` of one tube); appends its glitch, jump and gap
    truth tables to ``truth``."""
    # det_cal as SO's real data always has it (tau_eff 0 for instantaneous detectors), so
    # that a site config deconvolving time constants runs on every simulated dataset
    writer.add_detector_metadata(obs_id, tube, metadata_positions(dets, flaws), tau=flaws.tau_meta)
    pattern = config.scan
    writer.add_observation(obs_id, {
        "timestamp": tl.timestamps[0], "duration": tl.timestamps[-1] - tl.timestamps[0],
        "start_time": tl.timestamps[0], "stop_time": tl.timestamps[-1],
        "n_samples": len(tl.timestamps), "sample_rate": tl.sample_rate, "telescope": "lat",
        "tube_slot": tube, "tube_flavor": focal_plane.tube_flavor(tube)[4:].lower(),
        "wafer_slots_list": ",".join(sorted(set(dets["wafer_slot"]))), "type": "obs",
        "subtype": "cmb", "el_nom": pattern.el, "az_center": pattern.az_center,
        "az_throw": pattern.az_throw, "scan_speed": pattern.sky_speed})
    daz, el_det = horizon_offsets(dets["xi"], dets["eta"], tl.el[0])
    for wafer in sorted(set(dets["wafer_slot"])):
        in_wafer = dets["wafer_slot"] == wafer
        bands = [b for b in sorted(set(dets["bandpass"][in_wafer])) if f"{wafer}_{b}" in detsets]
        if not bands:
            continue
        glitches = draw_glitches(config.glitches, obs_id, wafer, tl.timestamps,
                                 dets["readout_id"][in_wafer],
                                 rng_for(config.seed, GLITCHES, block, wafer))
        truth["glitches"].append(glitches)
        for band_name in bands:
            sel = np.flatnonzero(in_wafer & (dets["bandpass"] == band_name))
            jumps, gaps = _simulate_detset(
                config, writer, sky, tl, obs_id, f"{wafer}_{band_name}",
                {k: v[sel] for k, v in dets.items()}, daz[sel], el_det[sel],
                sources.band(band_name), glitches, flaws.subset(sel), progress, workers)
            truth["jumps"].append(jumps)
            truth["gaps"].append(gaps)


def _simulate_detset(config, writer, sky, tl: Timeline, obs_id, detset, dets, daz, el_det,
                     sources: _Sources, glitches, flaws: DetectorFlaws, progress, workers=1):
    """Write the TOD of one detset, chunk by chunk of detectors; returns its jumps' and gaps'
    truth."""
    band = get_band(dets["bandpass"][0])
    white_rms = float(config.noise.white_mjy[band.name]) * flaws.noise_factor
    center = (dets["xi"].mean(), dets["eta"].mean())
    radius = np.hypot(dets["xi"] - center[0], dets["eta"] - center[1]).max()
    bore_q = tl.bore_q
    crossings = source_crossings(tl.timestamps, bore_q, sources.flares, center, radius, band.sigma)
    crossings += source_crossings(tl.timestamps, bore_q, sources.point_sources, center, radius,
                                  band.sigma, steady=True)
    crossings += moving_crossings(tl.timestamps, bore_q, sources.moving, center,
                                  radius + BEAM_REACH_SIGMA * band.sigma)
    atm_scale = (sky.atmosphere_scale(band, float(config.noise.white_mjy[band.name]), tl)
                 if sky.atm is not None else 0.0)
    ndet, nsamp = len(dets["xi"]), len(tl.timestamps)
    jumps = draw_jumps(config.jumps, obs_id, dets["readout_id"], tl.timestamps, white_rms,
                       rng_for(config.seed, JUMPS, obs_id, detset))
    gaps = draw_gaps(config.gaps, obs_id, dets["readout_id"], tl.timestamps,
                     rng_for(config.seed, GAPS, obs_id, detset))
    dead_rms = np.float32(config.detector_yield.dead_noise * config.noise.white_mjy[band.name])
    path = writer.tod_path(obs_id, detset)
    slices = [slice(s, min(s + DETS_PER_CHUNK, ndet)) for s in range(0, ndet, DETS_PER_CHUNK)]

    def add_noise(tod, sl):
        if not config.noise.enabled:
            return
        for i, name in enumerate(dets["readout_id"][sl]):
            rms = white_rms[sl][i]
            rng = rng_for(config.seed, WHITE, obs_id, name)
            tod[i] += rng.standard_normal(nsamp, dtype=np.float32) * np.float32(rms)
            fknee = flaws.fknee[sl][i]
            if fknee > 0:
                tod[i] += (rms * one_over_f(rng_for(config.seed, ONE_OVER_F, obs_id, name), nsamp,
                                            1 / tl.sample_rate, fknee, config.noise.alpha)
                           ).astype(np.float32)

    def add_sky(tod, sl):
        if sky.atm is not None:
            tod += np.float32(atm_scale) * sky.atm.sample(tl.t_rel, tl.az, daz[sl], el_det[sl])
        if sky.cmb is not None:
            tod += sky.cmb.sample(band, tl.sight, dets["xi"][sl], dets["eta"][sl],
                                  dets["gamma"][sl])
        add_sources(tod, dets["xi"][sl], dets["eta"][sl], crossings, band.sigma)

    def chunk(sl):
        tod = np.zeros((sl.stop - sl.start, nsamp), dtype=np.float32)
        if flaws.filters_sky:     # calibration and time constants act on the sky alone
            add_sky(tod, sl)
            respond_to_sky(tod, flaws.subset(sl), 1 / tl.sample_rate)
            add_noise(tod, sl)
        else:                     # the historical order: ideal detectors give identical data
            add_noise(tod, sl)
            add_sky(tod, sl)
        names = dets["readout_id"][sl]
        # a dead detector sees no sky but its readout still records noise, jumps, cosmic rays
        silence_dead(tod, flaws.subset(sl), config.detector_yield, (lambda row: dead_rms * rng_for(
            config.seed, DEAD_NOISE, obs_id, names[row]).standard_normal(nsamp)) if dead_rms
            else None)
        add_glitches(tod, names, tl.timestamps, glitches, config.glitches.time_constant)
        add_jumps(tod, names, jumps)
        add_gaps(tod, names, gaps)
        return tod

    bar = tqdm(total=len(slices), desc=f"{obs_id} {detset}", unit="chunk",
               disable=not progress, leave=False)
    with TodWriter(path, obs_id, detset, dets["readout_id"], tl.timestamps, tl.az, tl.el,
                   np.zeros(nsamp)) as out, ThreadPoolExecutor(workers) as pool:
        # at most 2 x workers chunks in flight; written in order by this thread
        for batch in range(0, len(slices), 2 * workers):
            todo = slices[batch:batch + 2 * workers]
            for sl, tod in zip(todo, pool.map(chunk, todo)):
                out.write_rows(sl.start, tod)
                bar.update()
    bar.close()
    writer.add_detset_file(obs_id, detset, dets["readout_id"], path, nsamp)
    return jumps, gaps
