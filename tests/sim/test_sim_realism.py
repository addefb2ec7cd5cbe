"""The simulated instrument's imperfections: each option does what it says, off changes nothing.

Small simulations (one wafer-band, 860 detectors, at most a minute of data, 220 Hz). Tolerances
are a few standard errors of each measured quantity, worked out in the comment next to it.
"""
from pathlib import Path

import h5py
import numpy as np
import pytest
from astropy import units as u
from astropy.coordinates import SkyCoord
from astropy.table import Table
from scipy import signal as sps
from scipy.optimize import curve_fit
from scipy.stats import exponnorm
from sotodlib import core
from sotodlib.tod_ops.filters import fourier_filter, timeconst_filter

from so_transients.common.bands import get_band
from so_transients.sim import focal_plane
from so_transients.sim.config import SimConfig, load_config
from so_transients.sim.simulate import simulate

from tests.conftest import run_sim

OBS = "obs_1700000000_lati1_111"
REALISTIC = Path(__file__).parents[2] / "configs/sim_realistic.yaml"
ONE_DETSET = dict(instrument={"tubes": ["i1"], "wafers": ["w16"], "bands": ["f090"]},
                  atmosphere={"enabled": False}, cmb={"enabled": False})
SKY_ONLY = dict(ONE_DETSET, noise={"enabled": False})
WHITE = get_band("f090").white_noise_mjy
FS = 220.0
SOURCE_DET = "w16_f090_p200A"
SOURCE = {"list": [{"at_detector": SOURCE_DET, "at_time": 30.0, "flux_mjy": 50000.0}]}
EVERY_OPTION_OFF = dict(
    noise={"white_scatter": 0.0, "fknee": None},
    detector_yield={"dead_fraction": 0.0, "noisy_fraction": 0.0},
    calibration={"scatter": 0.0}, time_constants={"tau_ms": None},
    focal_plane_errors={"sigma_arcsec": 0.0}, jumps={"rate_per_hour": 0.0},
    moving_sources={"list": []})


def sim(path, seed=1, duration=10.0, base=ONE_DETSET, **sections):
    return run_sim(path, seed=seed, observation={"duration": duration}, **{**base, **sections})


def tod(result, detset="w16_f090", obs_id=OBS):
    """(readout ids, signal) of one detset, read straight from its file."""
    with h5py.File(result.context.parent / f"tod/{obs_id}/{obs_id}_{detset}.h5") as f:
        return f["readout_id"][()].astype(str), f["signal"][()]


def truth(result, name):
    return Table.read(result.context.parent / f"truth/{name}.ecsv")


def readout_of(det_id):
    dets = focal_plane.wafer_detectors("i1", "w16")
    return dets["readout_id"][list(dets["det_id"]).index(det_id)]


def row_of(names, det_id):
    return int(np.flatnonzero(names == readout_of(det_id))[0])


def test_every_option_off_is_the_ideal_simulation(tmp_path):
    """Defaults leave data unchanged: naming every new option, switched off, gives bit-identical
    TOD and metadata and writes no new truth file."""
    cfg = dict(instrument={"bands": ["f090"]}, flares={"n": 2}, point_sources={"n": 1},
               glitches={"enabled": True, "rate_per_hour": 500})
    ideal = sim(tmp_path / "ideal", seed=7, base={}, **cfg)
    off = sim(tmp_path / "off", seed=7, base={}, **cfg, **EVERY_OPTION_OFF)
    assert np.array_equal(tod(ideal)[1], tod(off)[1])
    for result in (ideal, off):
        folder = result.context.parent
        assert sorted(p.name for p in (folder / "truth").iterdir()) == [
            "flares.ecsv", "glitches.ecsv", "point_sources.ecsv"]
    meta = [core.Context(str(r.context)).get_meta(OBS) for r in (ideal, off)]
    fp = [m.focal_plane for m in meta]
    assert np.array_equal(fp[0].xi, fp[1].xi) and np.array_equal(fp[0].eta, fp[1].eta)
    # det_cal as real data has it, with instantaneous detectors (tau_eff 0)
    assert all(np.all(np.asarray(m.det_cal.tau_eff) == 0) for m in meta)
    assert SimConfig.from_dict(EVERY_OPTION_OFF).to_dict() == SimConfig().to_dict()


@pytest.mark.parametrize("mode,value", [("zeros", 0.0), ("nan", np.nan), ("constant", -7.5)])
def test_dead_detectors(tmp_path, mode, value):
    result = sim(tmp_path, detector_yield={"dead_fraction": 0.1, "dead_mode": mode,
                                           "dead_value": -7.5})
    names, signal = tod(result)
    dead_rows = np.all(np.isnan(signal) if mode == "nan" else signal == value, axis=1)
    # exactly round(0.1 x 860) = 86 detectors are dead: the fraction is within half a detector
    assert abs(dead_rows.mean() - 0.1) <= 0.5 / len(names)
    dets = truth(result, "detectors")
    assert set(names[dead_rows]) == set(dets["readout_id"][dets["status"] == "dead"])
    assert np.all(np.isfinite(signal[~dead_rows]))


def test_noisy_detectors_and_white_noise_scatter(tmp_path):
    result = sim(tmp_path, duration=20.0, noise={"white_scatter": 0.1},
                 detector_yield={"noisy_fraction": 0.1, "noisy_factor": 10.0})
    names, signal = tod(result)
    dets = truth(result, "detectors")
    assert np.array_equal(dets["readout_id"], names)
    rms = signal.std(axis=1)
    noisy = dets["status"] == "noisy"
    assert noisy.sum() == 86
    # each rms from 4400 samples has a relative error 1/sqrt(2 x 4400) = 1.1 %: 5 sigma = 5.5 %
    assert np.all(np.abs(rms / (WHITE * dets["noise_factor"]) - 1) < 0.055)
    # noisy over the rest, geometric means: log-normal scatter 0.1 over 86 and 774 detectors
    # gives an error 0.1 x sqrt(1/86 + 1/774) = 1.1 %; 4 sigma = 4.5 %
    ratio = np.exp(np.log(rms[noisy]).mean() - np.log(rms[~noisy]).mean())
    assert abs(ratio / 10.0 - 1) < 0.045
    # the scatter of 774 detectors' log levels: relative error 1/sqrt(2 x 774) = 2.5 %, plus the
    # 1.1 % measurement error in quadrature (0.6 % bias); 10 % is 4 sigma
    assert abs(np.log(rms[~noisy]).std() / 0.1 - 1) < 0.10


def test_per_detector_one_over_f_knee(tmp_path):
    result = sim(tmp_path, duration=120.0, noise={"fknee": [0.5, 2.0], "alpha": 1.0})
    names, signal = tod(result)
    fknee = truth(result, "detectors")["fknee"]
    freq, psd = sps.welch(signal, fs=FS, nperseg=2**11)
    high = (freq > 20) & (freq < 100)
    # the white level, taking out the 1/f tail (up to 4 % of the power there)
    white = (psd[:, high].mean(axis=1) / (1 + fknee * (1 / freq[high]).mean()))[:, None]
    band = (freq > 0.1) & (freq < 1.0)    # 9 bins around the knees
    # alpha = 1: the 1/f power over the white one is fknee / f
    ratio = (freq[band] * (psd[:, band] / white - 1)).mean(axis=1) / fknee
    # each bin's power is known to 1/sqrt(25 Welch segments) = 20 %, which the subtraction of
    # the white level inflates where f > fknee: ~17 % per detector. The median of 860 is then
    # known to ~1 %, plus a few per cent from the Hann window's leakage: 5 %
    assert abs(np.median(ratio) - 1) < 0.05
    # each detector follows its own knee: the knees spread by 0.40 in log (log-uniform over a
    # factor 4), the estimates scatter about them by ~0.17
    assert np.log(ratio).std() < 0.25
    # the white level is untouched (860 detectors x 370 bins x 25 segments: known to 0.1 %)
    assert abs(np.sqrt(np.median(white) * FS / 2) / WHITE - 1) < 0.01


def test_calibration_scatter_scales_the_sky(tmp_path):
    """With noise off, every sample is the ideal sky times the detector's gain."""
    ideal = sim(tmp_path / "ideal", duration=40.0, base=SKY_ONLY, point_sources=SOURCE)
    scattered = sim(tmp_path / "cal", duration=40.0, base=SKY_ONLY, point_sources=SOURCE,
                    calibration={"scatter": 0.03, "distribution": "gaussian"})
    names, sky = tod(ideal)
    gain = truth(scattered, "detectors")["gain"]
    seen = tod(scattered)[1]
    hit = np.abs(sky).max(axis=1) > 1.0
    assert hit.sum() > 10
    assert np.allclose(seen[hit], sky[hit] * gain[hit][:, None].astype(np.float32), rtol=1e-6,
                       atol=1e-3)
    i = row_of(names, SOURCE_DET)
    assert abs(seen[i].max() / 50000.0 / gain[i] - 1) < 1e-3
    # rms of 860 Gaussian draws: relative error 1/sqrt(2 x 860) = 2.4 %; 4 sigma = 10 %
    assert abs(np.std(gain - 1) / 0.03 - 1) < 0.10
    # the metadata still state the nominal focal plane and no calibration: det_cal holds
    # the (zero) time constants only
    meta = core.Context(str(scattered.context)).get_meta(OBS)
    assert set(meta.det_cal._fields) == {"tau_eff"}


def _emg(t, amp, t0, sigma, tau):
    """A Gaussian crossing of peak ``amp`` seen through a one-pole time constant ``tau``."""
    return amp * sigma * np.sqrt(2 * np.pi) * exponnorm.pdf(t, tau / sigma, loc=t0, scale=sigma)


def test_time_constant_fitted_on_a_bright_crossing(tmp_path):
    result = sim(tmp_path, duration=40.0, point_sources=SOURCE, time_constants={"tau_ms": [1, 5]})
    names, signal = tod(result)
    i = row_of(names, SOURCE_DET)
    tau = truth(result, "detectors")["tau"][i]
    t = np.arange(signal.shape[1]) / FS
    near = np.abs(t - 30.0) < 0.15
    # the crossing's true time is known (30 s: the source was put on the detector's path then),
    # so tau is measured by the delay of the crossing (the mean delay of a one-pole filter is tau)
    model = lambda t, amp, sigma, tau: _emg(t, amp, 30.0, sigma, tau)
    popt, pcov = curve_fit(model, t[near], signal[i, near], p0=[50000.0, 0.016, 0.002],
                           sigma=np.full(near.sum(), WHITE), absolute_sigma=True)
    err = np.sqrt(pcov[2, 2])
    # 50 Jy over 367 mJy noise per sample, ~7 samples in the beam: the delay of a 16 ms crossing
    # is known to ~16 ms / (136 x sqrt(7)) ~ 0.05 ms; 5 sigma of the fit's own error
    assert err < 0.1e-3
    assert abs(popt[2] - tau) < 5 * err, (popt[2], tau, err)


def test_time_constants_in_det_cal_undo_with_sotodlib(tmp_path):
    """``det_cal.tau_eff`` is where sotodlib's timeconst_filter reads it; deconvolving with it
    gives back the instantaneous detector's crossing."""
    ideal = sim(tmp_path / "ideal", duration=40.0, base=SKY_ONLY, point_sources=SOURCE)
    slow = sim(tmp_path / "slow", duration=40.0, base=SKY_ONLY, point_sources=SOURCE,
               time_constants={"tau_ms": [1, 5]})
    aman = core.Context(str(slow.context)).get_obs(OBS, dets=[readout_of(SOURCE_DET)])
    dets = truth(slow, "detectors")
    tau = dets["tau"][dets["det_id"] == SOURCE_DET][0]
    assert aman.det_cal.tau_eff[0] == tau and 1e-3 <= tau <= 5e-3
    fixed = fourier_filter(aman, timeconst_filter(timeconst="det_cal.tau_eff", invert=True))
    names, sky = tod(ideal)
    want = sky[row_of(names, SOURCE_DET)]
    before = np.abs(aman.signal[0] - want).max()
    after = np.abs(fixed[0] - want).max()
    # a lag tau on a crossing of peak A and time sigma s moves samples by up to about
    # tau x A exp(-1/2) / s (1.9 Jy for 1 ms); deconvolved, what is left is the part of the
    # Gaussian beyond Nyquist, far below 1e-4 of the peak
    slope = 50000.0 * np.exp(-0.5) / (get_band("f090").sigma / np.radians(1.0))
    assert before > 0.5 * tau * slope and after < 1e-4 * 50000.0, (before, after)


def test_focal_plane_errors_are_in_the_metadata_only(tmp_path):
    result = sim(tmp_path, duration=40.0, base=SKY_ONLY, point_sources=SOURCE,
                 focal_plane_errors={"sigma_arcsec": 5.0})
    meta = core.Context(str(result.context)).get_meta(OBS)
    true = focal_plane.wafer_detectors("i1", "w16")
    index = {rid: k for k, rid in enumerate(true["readout_id"])}
    k = [index[d] for d in meta.dets.vals]
    offsets = np.degrees(np.r_[meta.focal_plane.xi - true["xi"][k],
                               meta.focal_plane.eta - true["eta"][k]]) * 3600
    # rms of 2 x 860 Gaussian offsets: relative error 1/sqrt(2 x 1720) = 1.7 %; 4 sigma ~ 7 %
    assert abs(np.sqrt(np.mean(offsets**2)) / 5.0 - 1) < 0.07
    dets = truth(result, "detectors")
    order = [list(dets["readout_id"]).index(d) for d in meta.dets.vals]
    assert np.allclose(dets["dxi"][order], offsets[:len(k)], atol=1e-6)
    # the TOD is simulated with the true positions: the source placed on the detector's true
    # path peaks at its full flux there
    names, signal = tod(result)
    assert abs(signal[row_of(names, SOURCE_DET)].max() / 50000.0 - 1) < 1e-3


def test_jump_heights_match_the_truth(tmp_path):
    result = sim(tmp_path, duration=20.0, jumps={"rate_per_hour": 180, "height": [20, 50],
                                                 "units": "white"})
    names, signal = tod(result)
    jumps = truth(result, "jumps")
    # 860 detectors x 20 s at 180 per hour: 860 jumps expected (Poisson, +- 30)
    assert 700 < len(jumps) < 1020
    assert np.all((np.abs(jumps["height"]) >= 20 * WHITE) & (np.abs(jumps["height"]) <= 50 * WHITE))
    n = 200
    row = {name: k for k, name in enumerate(names)}
    checked = 0
    for readout_id in np.unique(jumps["readout_id"]):
        mine = jumps[jumps["readout_id"] == readout_id]
        if len(mine) != 1 or not n <= mine["sample"][0] <= signal.shape[1] - n:
            continue
        s = mine["sample"][0]
        x = signal[row[readout_id]]
        step = x[s:s + n].mean() - x[s - n:s].mean()
        # difference of two means of 200 white samples: sigma = 367 x sqrt(2 / 200) = 37 mJy;
        # 5 sigma over several hundred jumps
        assert abs(step - mine["height"][0]) < 5 * WHITE * np.sqrt(2 / n)
        checked += 1
    assert checked > 200
    in_mjy = sim(tmp_path / "mjy", duration=20.0, jumps={"rate_per_hour": 180, "height": 1000,
                                                         "units": "mjy"})
    assert np.allclose(np.abs(in_mjy.jumps["height"]), 1000.0)


def test_moving_source_track_and_signal(tmp_path):
    rate = 30.0   # arcmin per minute
    result = sim(tmp_path, duration=40.0, base=SKY_ONLY, moving_sources={"list": [
        {"at_detector": SOURCE_DET, "at_time": 30.0, "flux_mjy": 20000.0,
         "rate_arcmin_per_min": rate, "direction_deg": 45.0}]})
    track = truth(result, "moving_source_tracks")
    sky = SkyCoord(track["ra"], track["dec"])
    step = sky[:-1].separation(sky[1:]).to_value("arcmin") / np.diff(track["ctime"].value)
    # a great circle at a constant rate: exact up to rounding
    assert np.allclose(step * 60, rate, rtol=1e-6)
    assert sky[0].separation(sky[-1]).to_value("arcmin") == pytest.approx(rate * 40 / 60, 1e-4)
    # it passes through the listed position at the listed time, heading north-east...
    src = result.moving_sources[0]
    k = int(np.argmin(np.abs(track["ctime"].value - src["t_ref"])))
    assert sky[k].position_angle(sky[-1]).deg == pytest.approx(45.0, abs=1e-4)
    assert src["t_ref"] == pytest.approx(1_700_000_030.0)
    assert sky[k].separation(SkyCoord(src["ra"] * u.rad, src["dec"] * u.rad)).arcsec < 1e-3
    # ...where the detector points: it records the full flux there
    names, signal = tod(result)
    assert abs(signal[row_of(names, SOURCE_DET), int(round(30.0 * FS))] / 20000.0 - 1) < 1e-3


def test_realistic_config_loads_and_is_reproducible(tmp_path):
    config = load_config(REALISTIC)
    assert config.noise.white_scatter > 0 and config.noise.fknee is not None
    assert config.detector_yield.dead_fraction > 0 and config.detector_yield.noisy_fraction > 0
    assert config.calibration.scatter > 0 and config.time_constants.tau_ms is not None
    assert config.focal_plane_errors.sigma_arcsec > 0 and config.jumps.rate_per_hour > 0
    assert config.glitches.enabled and config.moving_sources.list and config.point_sources.list
    data = config.to_dict()
    data["observation"].update(duration=10.0, n_obs=1)
    data["instrument"] = {"tubes": ["i1"], "wafers": ["w16"], "bands": ["f090", "f150"]}
    full = simulate(SimConfig.from_dict({**data, "output": str(tmp_path / "full")}),
                    progress=False)
    alone = simulate(SimConfig.from_dict({**data, "output": str(tmp_path / "alone")}),
                     progress=False, detsets=["w16_f090"])
    # same seed, same detectors: identical data and truth, whatever else is simulated
    assert np.array_equal(tod(full)[1], tod(alone)[1], equal_nan=True)
    f090 = full.detectors["bandpass"] == "f090"
    assert np.array_equal(full.detectors[f090]["gain"], alone.detectors[f090]["gain"])
    assert np.array_equal(full.jumps[np.char.startswith(full.jumps["readout_id"], "w16_f090")],
                          alone.jumps)
    for name in ("detectors", "jumps", "moving_sources", "moving_source_tracks"):
        assert len(truth(full, name)) > 0
    assert (full.context.parent / "metadata/det_cal.sqlite").exists()


@pytest.mark.parametrize("section,value,match", [
    ("time_constants", {"tau": 1.0}, "unknown keys"),
    ("detector_yield", {"dead_mode": "broken"}, "dead_mode"),
    ("detector_yield", {"dead_fraction": 1.5}, "dead_fraction"),
    ("calibration", {"distribution": "uniform"}, "distribution"),
    ("jumps", {"units": "K"}, "units"),
])
def test_bad_realism_keys_are_refused(section, value, match):
    with pytest.raises(ValueError, match=match):
        SimConfig.from_dict({section: value})


def test_unknown_moving_source_keys_are_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown keys"):
        sim(tmp_path, moving_sources={"list": [{"ra": 10.0, "dec": -5.0, "flux_mjy": 1.0,
                                                "rate_arcmin_per_min": 1.0, "speed": 3}]})


def test_imperfections_meet_on_every_channel(tmp_path):
    """Each imperfection is drawn on every channel independently, as on a real wafer: a dead
    detector records zeros plus its readout's noise, jumps and cosmic rays; lost channels are
    NaN throughout; gaps are NaN stretches; ``jumps.fraction`` of the channels jump once more."""
    result = sim(tmp_path, duration=20.0, base=SKY_ONLY, glitches={
        "enabled": True, "rate_per_hour": 3600.0, "n_dets": [400, 400],
        "amplitude_mjy": [5000.0, 5000.0]},
        detector_yield={"dead_fraction": 0.2, "dead_noise": 0.05, "lost_detectors": 2},
        jumps={"fraction": 0.5, "height": 5000.0, "units": "mjy"},
        gaps={"rate_per_hour": 720.0, "duration": 1.0})
    ids, data = tod(result, "w16_f090")
    dets = truth(result, "detectors")
    status = dict(zip(dets["readout_id"], dets["status"]))
    row = {name: i for i, name in enumerate(ids)}
    dead = [row[n] for n, s in status.items() if s == "dead" and n in row]
    lost = [row[n] for n, s in status.items() if s == "lost" and n in row]
    assert len(lost) == 2 and np.isnan(data[lost]).all()
    jumps, glitches, gaps = truth(result, "jumps"), truth(result, "glitches"), truth(result, "gaps")
    assert len(gaps) > 0           # 720 per hour for 20 s: a Poisson draw of mean 4
    for gap in gaps:
        k = row[gap["readout_id"]]
        assert np.isnan(data[k, gap["sample"]:gap["sample"] + gap["n_samples"]]).all()
    # half the channels jump once (the rate is 0): dead ones among them
    assert len(jumps) == len(ids) // 2
    jumped_dead = [row[n] for n in jumps["readout_id"] if row[n] in dead]
    assert jumped_dead
    for k in jumped_dead:
        j = jumps[jumps["readout_id"] == ids[k]][0]
        step = np.nanmedian(data[k, j["sample"]:]) - np.nanmedian(data[k, :j["sample"]])
        # the step over a readout noise of 0.05 x the white noise (~80 mJy): a few mJy off
        assert abs(step - j["height"]) < 50.0
    # the cosmic rays hit dead channels too: 400 of the 1720 wafer detectors per event
    hit = {n for ids_ in glitches["readout_ids"] for n in str(ids_).split(",")}
    dead_hit = [k for k in dead if ids[k] in hit]
    assert dead_hit and all(np.nanmax(np.abs(data[k])) > 1000.0 for k in dead_hit)
    # and a dead channel's readout noise is 0.05 of the band's white noise
    quiet = [k for k in dead if ids[k] not in hit and ids[k] not in set(jumps["readout_id"])]
    if quiet:
        assert np.nanstd(data[quiet]) == pytest.approx(0.05 * WHITE, rel=0.05)
