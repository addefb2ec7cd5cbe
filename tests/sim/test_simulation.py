"""The simulator end to end: noise statistics, injected sources, reproducibility, Context."""
import h5py
import numpy as np
import pytest
from astropy.table import Table
from scipy import signal as sps
from scipy.optimize import curve_fit
from scipy.spatial import cKDTree
from scipy.stats import norm
from sotodlib import core
from sotodlib.tod_ops import fft_ops

from so_transients.common.bands import get_band
from so_transients.sim import focal_plane
from so_transients.sim.config import SimConfig
from so_transients.sim.simulate import simulate

from tests.conftest import run_sim

OBS = "obs_1700000000_lati1_111"


def load(result, wafer="w16", band="f090", obs_id=OBS):
    ctx = core.Context(str(result.context))
    return ctx.get_obs(obs_id, dets={"wafer_slot": wafer, "bandpass": band})


@pytest.mark.parametrize("band", ["f090", "f150"])
def test_white_noise_level(noisy_dataset, band):
    aman = load(noisy_dataset, band=band)
    f, p = sps.welch(aman.signal[:100], fs=220.0, nperseg=4096)
    white = np.sqrt(p[:, (f > 20) & (f < 100)].mean(axis=1) * 220.0 / 2)
    # 100 detectors x ~1000 averaged bins: the mean is known to far better than 1 %
    assert abs(np.mean(white) / get_band(band).white_noise_mjy - 1) < 0.03


def test_uhf_white_noise_levels(tmp_path):
    result = run_sim(tmp_path, seed=4, observation={"duration": 60.0},
                     instrument={"tubes": ["c1"], "wafers": ["w00"]},
                     atmosphere={"enabled": False}, cmb={"enabled": False})
    for band in ("f220", "f280"):
        aman = load(result, "w00", band, obs_id="obs_1700000000_latc1_111")
        assert aman.samps.count == 60 * 340
        white = aman.signal[:100].std(axis=1)
        assert abs(np.mean(white) / get_band(band).white_noise_mjy - 1) < 0.03


def test_knee_frequency_from_sotodlib_noise_fit(noisy_dataset):
    aman = load(noisy_dataset)
    aman.restrict("dets", aman.dets.vals[::40])
    f, pxx = fft_ops.calc_psd(aman, nperseg=2**13, merge=False)
    fit = fft_ops.fit_noise_model(aman, f=f, pxx=pxx, wn_est=367 * np.sqrt(2 / 220),
                                  fknee_est=1.0, alpha_est=2.5, f_max=50, merge_fit=False)
    fknee, err = fit.fit[:, 1], np.sqrt(fit.cov[:, 1, 1])
    # Each detector's knee against 1.23 Hz in units of sotodlib's own fit error (~9 %: the
    # square root of its fit covariance's knee term). The 22 detectors see one atmosphere realization,
    # so their knees move together (measured 1.03-1.16 x 1.23 Hz, spread 3 %, pulls 0.4-1.5):
    # not independent, but a Bonferroni bound needs no independence: all 22 within
    # K of their errors fails falsely with < 1 % chance.
    k = norm.isf(0.01 / (2 * len(fknee)))
    assert np.all(np.abs(fknee - 1.23) < k * err), (fknee, err)


def test_neighbouring_detectors_share_the_atmosphere(noisy_dataset):
    aman = load(noisy_dataset)
    xy = np.c_[aman.focal_plane.xi, aman.focal_plane.eta]
    a_only = np.flatnonzero(aman.det_info.pol == "A")
    _, nn = cKDTree(xy[a_only]).query(xy[a_only], k=2)
    for i in a_only[:20:4]:
        j = a_only[nn[np.searchsorted(a_only, i), 1]]
        assert np.corrcoef(aman.signal[i], aman.signal[j])[0, 1] > 0.9


def test_steady_source_beam_profile(bright_source_dataset):
    aman = load(bright_source_dataset)
    det = list(aman.det_info.det_id).index("w16_f090_p200A")
    t = aman.timestamps - aman.timestamps[0]
    near = np.abs(t - 30.0) < 0.2
    gauss = lambda x, a, x0, s, c: a * np.exp(-0.5 * ((x - x0) / s) ** 2) + c
    popt, _ = curve_fit(gauss, t[near], aman.signal[det, near], p0=[5e4, 30.0, 0.02, 0])
    fwhm_deg = abs(popt[2]) * np.sqrt(8 * np.log(2)) * 1.0   # scan speed 1 deg/s on the sky
    assert abs(np.radians(fwhm_deg) / get_band("f090").fwhm - 1) < 0.05
    assert abs(popt[0] / 50000.0 - 1) < 0.05
    assert abs(popt[1] - 30.0) < 0.01


def test_flare_follows_light_curve_on_its_detector(bright_source_dataset):
    aman = load(bright_source_dataset)
    det = list(aman.det_info.det_id).index("w16_f090_p100A")
    t = aman.timestamps - aman.timestamps[0]
    k = np.argmin(np.abs(t - 60.0))
    # white noise is 367 mJy per sample: the peak sample is 20 Jy within a few sigma
    assert abs(aman.signal[det, k] - 20000.0) < 5 * 367
    truth = Table.read(bright_source_dataset.context.parent / "truth/flares.ecsv")
    assert len(truth) == 1 and truth["s_peak"].unit == "mJy" and truth["ra"].unit == "rad"
    assert np.isclose(truth["t_peak"][0], aman.timestamps[0] + 60.0)
    # before the flare starts the detector sees noise only
    early = np.abs(t - 55.0) < 0.5
    assert np.abs(aman.signal[det, early]).max() < 6 * 367


def test_context_round_trip(bright_source_dataset):
    aman = load(bright_source_dataset)
    path = bright_source_dataset.context.parent / f"tod/{OBS}/{OBS}_w16_f090.h5"
    with h5py.File(path) as f:
        names = f["readout_id"][()].astype(str)
        order = [list(names).index(d) for d in aman.dets.vals]
        assert np.array_equal(aman.signal, f["signal"][()][order])
        assert np.array_equal(aman.timestamps, f["timestamps"][()])
        assert np.array_equal(aman.boresight.az, f["boresight/az"][()])
    expected = focal_plane.wafer_detectors("i1", "w16")
    by_id = {rid: i for i, rid in enumerate(expected["readout_id"])}
    idx = [by_id[d] for d in aman.dets.vals]
    assert np.allclose(aman.focal_plane.xi, expected["xi"][idx])
    assert np.allclose(aman.focal_plane.gamma, expected["gamma"][idx])
    assert set(aman.det_info.wafer_slot) == {"w16"} and set(aman.det_info.bandpass) == {"f090"}
    assert aman.dets.count == 860 and aman.samps.count == 100 * 220
    assert "iir_params" in aman and "flags" in aman
    # a sample range and a detector subset load only what was asked
    ctx = core.Context(str(bright_source_dataset.context))
    sub = ctx.get_obs(OBS, dets=list(aman.dets.vals[5:8]), samples=(100, 300))
    assert np.array_equal(sub.signal, aman.signal[5:8, 100:300])
    obs = ctx.obsdb.get(OBS)
    assert obs["tube_slot"] == "i1" and obs["n_samples"] == 22000


def _signals(result):
    path = result.context.parent / f"tod/{OBS}/{OBS}_w16_f090.h5"
    with h5py.File(path) as f:
        return f["signal"][()]


def test_same_seed_same_data_and_different_seed_different(tmp_path):
    cfg = dict(observation={"duration": 20.0}, instrument={"bands": ["f090"]},
               flares={"n": 2}, point_sources={"n": 1}, glitches={"enabled": True,
                                                                   "rate_per_hour": 500})
    a = run_sim(tmp_path / "a", seed=7, **cfg)
    b = run_sim(tmp_path / "b", seed=7, **cfg)
    c = run_sim(tmp_path / "c", seed=8, **cfg)
    assert np.array_equal(_signals(a), _signals(b))
    assert len(a.glitches) > 0 and np.array_equal(a.glitches["ctime"], b.glitches["ctime"])
    assert not np.allclose(_signals(a), _signals(c))


def test_glitches_hit_many_detectors_at_one_instant(tmp_path):
    result = run_sim(tmp_path, seed=3, observation={"duration": 20.0},
                     instrument={"bands": ["f090"]}, atmosphere={"enabled": False},
                     cmb={"enabled": False}, noise={"enabled": False},
                     glitches={"enabled": True, "rate_per_hour": 1000})
    aman = load(result)
    glitch = result.glitches[0]
    hit = [d for d in glitch["readout_ids"].split(",") if d in set(aman.dets.vals)]
    assert len(hit) >= 5
    amps = dict(zip(glitch["readout_ids"].split(","), map(float, glitch["amplitudes"].split(","))))
    k = np.searchsorted(aman.timestamps, glitch["ctime"])
    decay = np.exp(-(aman.timestamps[k] - glitch["ctime"]) / 0.004)
    rows = [list(aman.dets.vals).index(d) for d in hit]
    assert np.allclose(aman.signal[rows, k], [amps[d] * decay for d in hit], rtol=1e-5)
    assert np.all(aman.signal[rows, k - 1] == 0)            # nothing before the instant
    others = np.setdiff1d(np.arange(aman.dets.count), rows)
    assert np.all(aman.signal[others, k] == 0) or len(result.glitches) > 1


def test_bad_configs_are_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown keys"):
        run_sim(tmp_path, scan={"speed": 2})
    with pytest.raises(ValueError, match="unknown LAT tube"):
        run_sim(tmp_path, instrument={"tubes": ["q7"]})
    with pytest.raises(ValueError, match="no detectors selected"):
        run_sim(tmp_path, instrument={"tubes": ["i1"], "wafers": ["w00"]})


def test_add_sources_is_the_beam_out_to_its_reach():
    """Every detector-sample pair within BEAM_REACH_SIGMA beam sigmas gets flux x beam; no
    other sample changes (checked against the plain formula on every pair)."""
    from so_transients.common.pointing import angular_distance_xieta
    from so_transients.sim.sources import BEAM_REACH_SIGMA, SourceCrossing, add_sources
    rng = np.random.default_rng(5)
    sigma = np.radians(0.93 / 60)
    xi, eta = rng.uniform(-0.004, 0.004, (2, 200)) + 0.03    # a wafer off the boresight
    track = SourceCrossing(np.arange(50, 650), np.linspace(0.025, 0.035, 600),
                           np.full(600, 0.0301), rng.uniform(100, 300, 600))
    tod = rng.standard_normal((200, 700)).astype(np.float32)
    expect = tod.copy()
    dist = angular_distance_xieta(xi[:, None], eta[:, None], track.xi, track.eta)
    beam = np.where(dist <= BEAM_REACH_SIGMA * sigma,
                    track.flux * np.exp(-0.5 * (dist / sigma) ** 2), 0.0)
    expect[:, track.samples] += beam.astype(np.float32)
    add_sources(tod, xi, eta, [track], sigma)
    assert 0 < np.count_nonzero(beam) < beam.size / 2
    assert np.array_equal(tod, expect)


def test_one_detset_alone_is_identical_to_the_full_simulation(tmp_path):
    """Campaigns simulate each group separately (to preprocess one while the next is being
    simulated): a detset written alone must equal the full dataset's."""
    cfg = dict(observation={"duration": 20.0}, instrument={"bands": ["f090", "f150"]},
               flares={"n": 3}, point_sources={"n": 1},
               glitches={"enabled": True, "rate_per_hour": 500})
    full = run_sim(tmp_path / "full", seed=7, **cfg)
    config = SimConfig.from_dict({"output": str(tmp_path / "alone"), "seed": 7, **cfg})
    alone = simulate(config, progress=False, detsets=["w16_f090"])
    assert alone.detsets == {OBS: ["w16_f090"]} and len(full.detsets[OBS]) > 1
    assert np.array_equal(_signals(alone), _signals(full))
    assert len(alone.glitches) and set(alone.glitches["wafer_slot"]) == {"w16"}
    assert load(alone).dets.count == load(full).dets.count
    with pytest.raises(ValueError, match="not simulated by this config"):
        simulate(config, progress=False, overwrite=True, detsets=["w16_f220"])
