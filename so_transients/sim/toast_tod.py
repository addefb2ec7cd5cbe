"""Time-ordered data from TOAST 3, a simulator this package did not write, as a dataset that
``sotodlib.core.Context`` opens like ours (``studies/toast_wafers.py``; the slow test
``tests/sim/test_toast_tod.py``). TOAST is optional: ``pip install toast``.

What TOAST makes: a hexagonal focal plane of ``n_pix`` dual-polarization pixels (one f090
wafer, ``width_deg`` across), a constant-elevation ground scan at the SO site
(:class:`toast.ops.SimGround`, with TOAST's own azimuth turnarounds and acceleration), its
noise model (white plus 1/f, :class:`toast.ops.SimNoise`) and its atmosphere
(:class:`toast.ops.SimAtmosphere`, a turbulent volume blown through the beams). What this
module adds: flares injected at TOAST's own detector pointing (each peaking as it crosses a
random detector, a Gaussian beam of the band's FWHM on the angle between the detector's
TOAST quaternion and the source), the detector imperfections of a simulation config
(:mod:`so_transients.sim.imperfections`: dead channels, noise scatter, gains, time
constants and det_cal errors, focal-plane errors, jumps, cosmic rays, NaN), and the files.
TOAST's ``SimCatalog`` is not used (it plays light curves backwards between epochs).

Pointing: TOAST runs in ``so3g_compat_mode`` (qpoint with so3g's weather) and the boresight
az/el it simulated is what the dataset records; :func:`pointing_difference` measures how far
sotodlib's pointing of that boresight and TOAST's focal plane is from TOAST's own detector
pointing (8" here, a constant of the two libraries' astrometry).

Units: TOAST's noise is configured so that its numbers are mJy (``net_mjy``, per root
second); its atmosphere, in K_CMB, is converted to mJy in the band's beam
(:func:`kcmb_to_mjy`).
"""
from __future__ import annotations

import datetime
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.table import Table

from so_transients.common.angles import ARCMIN, sky_separation
from so_transients.common.bands import CENTER_GHZ, get_band
from so_transients.common.flare_model import active_window, flare_flux
from so_transients.common.pointing import boresight_quats, radec_of_samples
from so_transients.io.tod_file import TodWriter
from so_transients.sim.config import SimConfig
from so_transients.sim.dataset import DatasetWriter, obs_id_for
from so_transients.sim.gaps import add_gaps, draw_gaps
from so_transients.sim.glitches import add_glitches, draw_glitches
from so_transients.sim.imperfections import (
    draw_flaws, flaws_table, metadata_positions, one_over_f, respond_to_sky, silence_dead
)
from so_transients.sim.jumps import add_jumps, draw_jumps
from so_transients.sim.simulate import rng_for
from so_transients.sim.sources import FLARE_COLUMNS

TUBE, WAFER = "t0", "w00"
SO_SITE = ("-22:57:30", "-67:47:10", 5200.0)       # lat, lon, altitude (m)


@dataclass
class ToastSetup:
    """One TOAST observation of one wafer-band."""

    start: float = 1748746800.0          # ctime (2025-06-01 03:00 UTC)
    duration: float = 360.0              # s
    sample_rate: float = 200.0           # Hz
    band: str = "f090"
    n_pix: int = 331                     # dual-polarization pixels (a hexagon of 10 rings)
    width_deg: float = 0.6               # the wafer's width on the sky
    az_min: float = 140.0                # deg: TOAST's scan, between these azimuths ...
    az_max: float = 160.0
    el: float = 50.0                     # ... at this elevation
    scan_rate: float = 1.0               # deg/s in azimuth
    scan_accel: float = 2.0              # deg/s^2 at the turnarounds
    net_mjy: float = 25.5                # white noise, mJy sqrt(s) (360 mJy per 200 Hz sample)
    fknee: float = 0.05                  # Hz, TOAST's 1/f noise ...
    alpha: float = 1.0                   # ... and its slope
    atmosphere: bool = True
    encoder_noise_arcsec: float = 0.5    # rms of the recorded azimuth: SO's encoders are not
    #                                      exact, TOAST's azimuth is, and sotodlib's scanspeed
    #                                      turnaround flags fail on a speed that never varies
    #                                      (the median of its steps above their 95th percentile
    #                                      is then of none)
    imperfections: dict = field(default_factory=dict)   # SimConfig sections (yield, jumps, ...)


@dataclass
class ToastResult:
    context: Path
    flares: Table
    detectors: Table
    pointing_arcsec: float               # largest sotodlib-vs-TOAST detector pointing difference


def kcmb_to_mjy(band) -> float:
    """mJy in the band's Gaussian beam per K_CMB at its centre frequency."""
    b = get_band(band)
    omega = 2 * np.pi * b.sigma ** 2 * u.sr
    per_sr = (1 * u.K).to(u.MJy / u.sr, u.thermodynamic_temperature(CENTER_GHZ[band] * u.GHz))
    return float((per_sr * omega).to_value(u.mJy))


def _observe(setup: ToastSetup, seed):
    """TOAST's observation: times, az, el (rad), detector names, their focal-plane
    quaternions, celestial pointing quaternions (ndet, nsamp, 4), and noise and atmosphere
    (ndet, nsamp; mJy)."""
    import toast
    import toast.ops
    from toast.instrument import GroundSite, Telescope
    from toast.instrument_sim import fake_hexagon_focalplane
    from toast.schedule import GroundSchedule, GroundScan

    band = get_band(setup.band)
    fs = setup.sample_rate * u.Hz
    fp = fake_hexagon_focalplane(
        n_pix=setup.n_pix, width=setup.width_deg * u.degree, sample_rate=fs,
        fwhm=band.fwhm / ARCMIN * u.arcmin, bandcenter=CENTER_GHZ[setup.band] * u.GHz,
        bandwidth=0.25 * CENTER_GHZ[setup.band] * u.GHz, psd_net=setup.net_mjy * u.K * u.s ** 0.5,
        psd_fmin=1e-5 * u.Hz, psd_fknee=setup.fknee * u.Hz, psd_alpha=setup.alpha,
        random_seed=seed)
    site = GroundSite("SO", SO_SITE[0], SO_SITE[1], SO_SITE[2] * u.meter)
    telescope = Telescope("LAT", focalplane=fp, site=site)
    start = datetime.datetime.fromtimestamp(setup.start, datetime.timezone.utc)
    stop = start + datetime.timedelta(seconds=setup.duration)
    scan = GroundScan("field", start, stop, 0 * u.degree, setup.az_min * u.degree,
                      setup.az_max * u.degree, setup.el * u.degree)
    schedule = GroundSchedule([scan], site_name="SO", telescope_name="LAT",
                              site_lat=site.earthloc.lat, site_lon=site.earthloc.lon,
                              site_alt=site.earthloc.height)
    data = toast.Data(toast.Comm(world=None))
    toast.ops.SimGround(telescope=telescope, schedule=schedule, weather="atacama",
                        median_weather=True, scan_rate_az=setup.scan_rate * u.degree / u.second,
                        scan_accel_az=setup.scan_accel * u.degree / u.second ** 2,
                        so3g_compat_mode=True, realization=seed).apply(data)
    toast.ops.DefaultNoiseModel().apply(data)
    toast.ops.SimNoise(det_data="noise", realization=seed).apply(data)
    if setup.atmosphere:
        azel = toast.ops.PointingDetectorSimple(boresight="boresight_azel", quats="quats_azel")
        toast.ops.SimAtmosphere(det_data="atm", detector_pointing=azel, realization=seed,
                                cache_dir=None).apply(data)
    toast.ops.PointingDetectorSimple(boresight="boresight_radec",
                                     quats="quats_radec").apply(data)
    ob = data.obs[0]
    dets = list(ob.local_detectors)
    noise = np.asarray(ob.detdata["noise"].data, np.float32)
    atm = (np.asarray(ob.detdata["atm"].data, np.float32) * np.float32(kcmb_to_mjy(setup.band))
           if setup.atmosphere else np.zeros_like(noise))
    return dict(times=np.array(ob.shared["times"].data), az=np.array(ob.shared["azimuth"].data),
                el=np.array(ob.shared["elevation"].data), dets=dets,
                fp_quats=np.array([fp[d]["quat"] for d in dets]),
                quats=np.array(ob.detdata["quats_radec"].data), noise=noise, atm=atm)


def _vectors(quats):
    """Unit pointing vectors of TOAST quaternions (..., 4)."""
    from toast import qarray
    shape = quats.shape[:-1]
    return qarray.rotate(quats.reshape(-1, 4), np.array([0.0, 0.0, 1.0])).reshape(*shape, 3)


def _radec(vectors):
    return np.arctan2(vectors[..., 1], vectors[..., 0]), np.arcsin(np.clip(vectors[..., 2], -1, 1))


def place_flares(obs, band, seed, n_bright=10, n_faint=5, bright=3000.0, faint=900.0,
                 t_rise=10.0, spacing=20.0) -> Table:
    """Flares peaking as they cross random detectors at random times, at least ``spacing``
    s apart and from the ends, while the boresight sweeps at its nominal speed (within 5 %,
    for 2 s either side: TOAST's short sweeps turn around every 20 s, and what the
    turnarounds cost is ``studies/configs/campaign_scan_ends.yaml``'s subject); positions
    from TOAST's pointing of that detector then."""
    rng = np.random.default_rng(2000 + seed)
    t = obs["times"]
    speed = np.abs(np.gradient(obs["az"], t))
    steady = np.abs(speed / np.median(speed) - 1) < 0.05
    reach = int(round(2.0 / np.median(np.diff(t))))
    steady = ~np.convolve(~steady, np.ones(2 * reach + 1), mode="same").astype(bool)
    slots = np.arange(t[0] + spacing, t[-1] - spacing, spacing)
    n = min(n_bright + n_faint, len(slots))
    times = []
    for start in np.sort(rng.choice(slots, n, replace=False)):
        window = np.flatnonzero(steady & (t >= start) & (t < start + spacing / 2))
        if len(window):
            times.append(float(t[rng.choice(window)]))
    n = len(times)
    fluxes = rng.permutation([bright] * n_bright + [faint] * n_faint)[:n]
    rows = []
    for k, (when, flux) in enumerate(zip(times, fluxes)):
        det, samp = int(rng.integers(len(obs["dets"]))), int(np.searchsorted(t, when))
        ra, dec = _radec(_vectors(obs["quats"][det, samp]))
        rows.append((k, band, float(ra) % (2 * np.pi), float(dec), float(t[samp]), float(flux),
                     t_rise, t_rise, 1.0, 1.0, 0.0))
    table = Table(rows=rows or None, names=[c[0] for c in FLARE_COLUMNS],
                  dtype=[c[1] if c[1] is not str else "U8" for c in FLARE_COLUMNS])
    for name, _, unit in FLARE_COLUMNS:
        if unit is not None:
            table[name].unit = unit
    return table


def flare_signal(obs, flares, band) -> np.ndarray:
    """The flares as TOAST's detectors see them (ndet, nsamp; mJy): the flare's light curve
    times a Gaussian beam of the band's width on the angle between each detector's TOAST
    pointing and the flare."""
    t, sigma = obs["times"], get_band(band).sigma
    out = np.zeros((len(obs["dets"]), len(t)), np.float32)
    for fl in flares:
        lo_t, hi_t = active_window(fl["t_peak"], fl["t_rise"], fl["t_decay"])
        lo, hi = np.searchsorted(t, [lo_t, hi_t])
        if hi <= lo:
            continue
        src = np.array([np.cos(fl["dec"]) * np.cos(fl["ra"]), np.cos(fl["dec"]) * np.sin(fl["ra"]),
                        np.sin(fl["dec"])])
        cosang = np.clip(_vectors(obs["quats"][:, lo:hi]) @ src, -1, 1)
        near = cosang > np.cos(8 * sigma)
        if not near.any():
            continue
        light = flare_flux(t[lo:hi], fl["t_peak"], fl["s_peak"], fl["t_rise"], fl["t_decay"],
                           fl["eta_rise"], fl["eta_decay"])
        beam = np.where(near, np.exp(-0.5 * (np.arccos(cosang) / sigma) ** 2), 0.0)
        out[:, lo:hi] += (beam * light[None, :]).astype(np.float32)
    return out


def xieta_of(fp_quats):
    """xi, eta, gamma (rad) of TOAST focal-plane quaternions (TOAST's SO convention)."""
    from toast.instrument_coords import quat_to_xieta
    return quat_to_xieta(np.asarray(fp_quats))


def pointing_difference(obs, xi, eta, n=200) -> float:
    """Largest angle (arcsec) between TOAST's detector pointing and sotodlib's (so3g, from
    the recorded boresight and the focal plane's xi, eta), over ``n`` samples of random
    detectors."""
    rng = np.random.default_rng(0)
    q = boresight_quats(obs["times"], obs["az"], obs["el"], np.zeros(len(obs["times"])))
    dets = rng.integers(len(obs["dets"]), size=n)
    samps = rng.integers(len(obs["times"]), size=n)
    ra, dec = radec_of_samples(q, xi, eta, dets, samps)
    tra, tdec = _radec(_vectors(obs["quats"][dets, samps]))
    return float(np.degrees(np.max(sky_separation(ra, dec, tra, tdec))) * 3600)


def simulate_toast(root, seed, setup: ToastSetup = ToastSetup(), flares=True) -> ToastResult:
    """A dataset at ``root`` from TOAST's observation (:class:`ToastSetup`), with flares
    (:func:`place_flares`) unless ``flares`` is False, and ``setup.imperfections``."""
    root = Path(root)
    obs = _observe(setup, seed)
    band = setup.band
    xi, eta, gamma = xieta_of(obs["fp_quats"])
    names = np.array(obs["dets"])
    ndet, nsamp = len(names), len(obs["times"])
    config = SimConfig.from_dict({**setup.imperfections, "seed": seed})
    dets = {"readout_id": names, "det_id": names, "tube_slot": np.full(ndet, TUBE),
            "wafer_slot": np.full(ndet, WAFER), "bandpass": np.full(ndet, band),
            "pol": np.array([n.split("-")[0][-1] for n in names]),
            "pixel": np.array([n.split("-")[0][1:-1] for n in names]),
            "xi": xi, "eta": eta, "gamma": gamma}
    flaws = draw_flaws(config, TUBE, dets, lambda *keys: rng_for(seed, "toast", *keys))
    table = place_flares(obs, band, seed) if flares else place_flares(obs, band, seed, 0, 0)
    dt = 1.0 / setup.sample_rate
    tod = obs["atm"] + flare_signal(obs, table, band)
    respond_to_sky(tod, flaws, dt)             # gains and time constants act on the sky
    tod += obs["noise"] * flaws.noise_factor[:, None].astype(np.float32)
    white = setup.net_mjy * np.sqrt(setup.sample_rate) * flaws.noise_factor
    for i in np.flatnonzero(flaws.fknee > 0):
        tod[i] += (white[i] * one_over_f(rng_for(seed, "toast_fknee", names[i]), nsamp, dt,
                                         flaws.fknee[i], config.noise.alpha)).astype(np.float32)
    obs_id = obs_id_for(setup.start, TUBE)
    yield_cfg = config.detector_yield
    dead_rms = yield_cfg.dead_noise * setup.net_mjy * np.sqrt(setup.sample_rate)
    silence_dead(tod, flaws, yield_cfg, (lambda row: dead_rms * rng_for(
        seed, "toast_dead", names[row]).standard_normal(nsamp)) if dead_rms else None)
    glitches = draw_glitches(config.glitches, obs_id, WAFER, obs["times"], names,
                             rng_for(seed, "toast_glitches"))
    add_glitches(tod, names, obs["times"], glitches, config.glitches.time_constant)
    jumps = draw_jumps(config.jumps, obs_id, names, obs["times"], white,
                       rng_for(seed, "toast_jumps"))
    add_jumps(tod, names, jumps)
    gaps = draw_gaps(config.gaps, obs_id, names, obs["times"], rng_for(seed, "toast_gaps"))
    add_gaps(tod, names, gaps)

    writer = DatasetWriter(root)
    writer.add_detector_metadata(obs_id, TUBE, metadata_positions(dets, flaws), tau=flaws.tau_meta)
    t = obs["times"]
    writer.add_observation(obs_id, {
        "timestamp": t[0], "duration": t[-1] - t[0], "start_time": t[0], "stop_time": t[-1],
        "n_samples": nsamp, "sample_rate": setup.sample_rate, "telescope": "lat",
        "tube_slot": TUBE, "tube_flavor": "mf", "wafer_slots_list": WAFER, "type": "obs",
        "subtype": "cmb", "el_nom": setup.el, "az_center": 0.5 * (setup.az_min + setup.az_max),
        "az_throw": 0.5 * (setup.az_max - setup.az_min), "scan_speed": setup.scan_rate})
    detset = f"{WAFER}_{band}"
    path = writer.tod_path(obs_id, detset)
    az = obs["az"] + np.radians(setup.encoder_noise_arcsec / 3600) * rng_for(
        seed, "toast_encoder").standard_normal(nsamp)
    with TodWriter(path, obs_id, detset, names, t, az, obs["el"], np.zeros(nsamp)) as out:
        out.write_rows(0, tod)
    writer.add_detset_file(obs_id, detset, names, path, nsamp)
    table.write(root / "truth" / "flares.ecsv", overwrite=True)
    detectors = flaws_table(dets, flaws)
    detectors.write(root / "truth" / "detectors.ecsv", overwrite=True)
    for name, truth in (("glitches", glitches), ("jumps", jumps), ("gaps", gaps)):
        truth.write(root / "truth" / f"{name}.ecsv", overwrite=True)
    context = writer.finish({"toast": {k: v for k, v in vars(setup).items()}, "seed": seed})
    return ToastResult(context, table, detectors, pointing_difference(obs, xi, eta))
