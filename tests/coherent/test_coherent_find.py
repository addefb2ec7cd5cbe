"""transient_find's coherent mode: maxima of Z become candidates; glitches are vetoed."""
import numpy as np
import pytest

from so_transients.coherent.config import CoherentConfig
from so_transients.coherent.statistic import row_offsets
from so_transients.coherent.find import scan_candidates
from so_transients.coherent.vetoes import shares

from tests.coherent.test_coherent import FS, SIGMA_BEAM, SPEED, inject, matched_pulse, wafer

NSAMP = 4000


def crossing(rng, flux=60.0, t0=2000):
    """White-noise S/N of a square wafer with one source crossing it at ``t0`` on a row."""
    geometry, sigma = wafer(rng=rng)
    rows = row_offsets(geometry, SIGMA_BEAM, CoherentConfig().row_step)
    c = rows[len(rows) // 2]
    snr = rng.normal(size=(len(sigma), NSAMP))
    inject(snr, geometry, sigma, flux, t0, c)
    return geometry, sigma, snr, c


def found(snr, geometry, sigma, **cfg):
    return scan_candidates(snr, 0, geometry, SIGMA_BEAM, sigma, np.ones(len(sigma), bool),
                           CoherentConfig(**cfg))


def test_a_faint_crossing_is_found_where_no_detector_reaches_snr_3():
    rng = np.random.default_rng(3)
    geometry, sigma, snr, c = crossing(rng)
    beam = np.exp(-0.5 * ((geometry.across - c) / SIGMA_BEAM) ** 2)
    # 60 mJy gives every detector at most S/N 60 / 20 = 3 and most of them under 1.5: the
    # paper's search needs 11 samples >= 3 on 5 detectors
    assert np.sum(60.0 * beam / sigma >= 3) < 5
    peaks = found(snr, geometry, sigma)
    at = [p for p in peaks if abs(p["sample"] - 2000) <= 3]
    assert len(at) == 1
    expected = 60.0 * np.sqrt(np.sum((beam * (np.abs(geometry.across - c)
                                              <= 3 * SIGMA_BEAM) / sigma) ** 2))
    # Z of the maximum: expected (about 11) plus unit noise, maximized over neighbours
    assert abs(at[0]["map_z"] - expected) < 3.0
    assert abs(at[0]["row"] - c) < 0.5 * SIGMA_BEAM
    # its hits are the detectors within hit_reach beam sigmas, at the samples it crosses them
    near = np.flatnonzero(np.abs(geometry.across - at[0]["row"]) <= 2.0 * SIGMA_BEAM)
    assert set(at[0]["hit_dets"]) == set(near)
    assert np.all(at[0]["hit_samples"] == at[0]["sample"] + geometry.lag_samples[
        at[0]["hit_dets"]])
    # noise alone in the rest of the scan: its maxima are few (Z >= 4.5 over ~100k
    # positions of which a few thousand independent: Gaussian odds ~ 0.01-0.1 each)
    assert len(peaks) - 1 <= 3


def test_a_glitch_on_every_detector_at_one_instant_is_vetoed():
    rng = np.random.default_rng(4)
    geometry, sigma, snr, _ = crossing(rng, flux=150.0)
    width = SIGMA_BEAM / SPEED * FS
    snr += 40.0 * matched_pulse(NSAMP, 3000, width)[None, :]     # every detector at once
    vetoed = found(snr, geometry, sigma)
    # the glitch is crossed at sample 3000 by detectors whose lag puts the position there
    lags = geometry.lag_samples
    near_glitch = lambda peaks: [p for p in peaks
                                 if np.any(np.abs(p["sample"] + lags - 3000) <= 2)
                                 and abs(p["sample"] - 2000) > 10]
    assert near_glitch(vetoed) == []
    assert any(abs(p["sample"] - 2000) <= 3 for p in vetoed)        # the source is kept
    # without the instant-share veto the glitch makes candidates (so the veto is what acts)
    assert near_glitch(found(snr, geometry, sigma, max_instant_share=1.0))


def test_a_spike_on_one_detector_is_vetoed():
    rng = np.random.default_rng(5)
    geometry, sigma = wafer(rng=rng)
    snr = rng.normal(size=(len(sigma), NSAMP))
    snr[100] += 80.0 * matched_pulse(NSAMP, 2500, SIGMA_BEAM / SPEED * FS)
    assert not [p for p in found(snr, geometry, sigma) if p["map_z"] > 8]
    assert [p for p in found(snr, geometry, sigma, max_single_share=1.0, max_instant_share=1.0,
                             chi2_bins=0)
            if p["map_z"] > 8]


def test_the_sign_inverted_maps_maxima_are_vetoed_as_the_datas():
    """transient_significance seeds the inverted maps' stacks with the maxima of -Z that
    the same vetoes keep: a negative source (a source of the inverted data) is kept, a
    negative glitch on every detector at one instant is not."""
    from so_transients.coherent.find import scan_map
    from so_transients.coherent.vetoes import peaks

    rng = np.random.default_rng(6)
    geometry, sigma, snr, _ = crossing(rng, flux=150.0)
    snr = -snr - 40.0 * matched_pulse(NSAMP, 3000, SIGMA_BEAM / SPEED * FS)[None, :]
    cfg = CoherentConfig()
    _, z, _, _, weights = scan_map(snr, geometry, SIGMA_BEAM, sigma, np.ones(len(sigma), bool),
                                   cfg, with_flux=False)
    lags = geometry.lag_samples

    def inverted(**vetoes):
        r, s = peaks(snr, geometry, -z, weights, SIGMA_BEAM, 4.5, cfg.row_step,
                     CoherentConfig(**vetoes).vetoes, sign=-1.0)
        at_source = any(abs(t - 2000) <= 3 for t in s)
        at_glitch = any(np.any(np.abs(t + lags - 3000) <= 2) and abs(t - 2000) > 10
                        for t in s)
        return at_source, at_glitch

    assert inverted() == (True, False)
    assert inverted(max_instant_share=1.0, chi2_bins=0)[1]   # the vetoes remove the glitch


@pytest.mark.parametrize("terms, lags, single, instant", [
    ([1.0, 1.0, 1.0, 1.0], [0, 10, 20, 30], 0.25, 0.25),
    ([1.0, 1.0, 1.0, 1.0], [0, 1, 2, 30], 0.25, 0.75),
    ([3.0, -1.0, 0.0, 0.0], [0, 10, 20, 30], 1.5, 1.0),
    ([], [], 1.0, 1.0),
])
def test_shares(terms, lags, single, instant):
    s, i = shares(np.asarray(terms, float), np.asarray(lags, int), 2)
    assert s == pytest.approx(single) and i == pytest.approx(instant)


# --- through the site pipeline and sotodlib's Pipeline -------------------------------------

COHERENT = {"transient_find": {"calc": {"mode": "coherent"}}}


def coherent_pipe():
    """The shipped site config's steps with ``transient_find`` in coherent mode."""
    import yaml

    from so_transients.site.pipeline import PAPER, apply_overrides
    return apply_overrides(yaml.safe_load(PAPER.read_text())["process_pipe"], COHERENT)


@pytest.fixture(scope="module")
def coherent_site_run(module_tmp, two_flare_dataset):
    """Five minutes of w16 at f090 with two flares, the shipped config in coherent mode."""
    from so_transients.site.pipeline import PAPER, run_site_pipeline, write_site_config

    root = module_tmp("coherent")
    sim = two_flare_dataset
    config = write_site_config(sim.context.parent, path=root / "preprocess.yaml",
                               overrides=COHERENT, results=root / "preprocess",
                               template=PAPER)
    run_site_pipeline(config)
    return sim, config


@pytest.mark.slow
def test_coherent_mode_runs_in_the_site_pipeline_into_the_archive(coherent_site_run):
    from so_transients.site.results import archive_table
    from so_transients.site.pipeline import failed_groups

    sim, config = coherent_site_run
    assert failed_groups(config) == ""
    table = archive_table(config, detected_only=False)
    assert len(table) and np.all(np.isfinite(table["map_z"]))
    assert np.all(table["map_z"] >= CoherentConfig().coherent_threshold)
    detected = table[np.asarray(table["detected"], bool)]
    for t_peak in sim.flares["t_peak"]:
        assert np.any(np.abs(detected["t_peak"] - t_peak) < 2.0)


def test_a_band_with_too_few_live_detectors_gets_a_named_warning(tmp_path, caplog):
    import logging

    from so_transients.common import candidates
    from tests.conftest import load_group, run_sim, run_steps

    sim = run_sim(tmp_path, seed=12, observation={"duration": 60.0},
                  instrument={"bands": ["f090"]}, atmosphere={"enabled": False},
                  cmb={"enabled": False})
    aman = load_group(sim, band="f090")
    aman.signal[3:] = 0.0                         # all but three detectors dead
    steps = [s for s in coherent_pipe()
             if s["name"] in candidates.STEPS or s["name"] == "transient_filter"]
    with caplog.at_level(logging.WARNING):
        run_steps(aman, steps)
    assert aman.transient_candidates.transient_cand.count == 0
    ran = [n for step in ("transient_find", "transient_cuts", "transient_fit")
           for n in candidates.names(step)]
    assert set(ran) <= set(aman.transient_candidates._fields)
    assert any("too few for a coherent search" in r.message and sim.obs_ids[0] in r.message
               and "f090" in r.message for r in caplog.records)


@pytest.mark.slow
def test_many_detector_glitches_do_not_become_coherent_detections(tmp_path):
    """Noise with 50 cosmic-ray glitches, each on 30-60 detectors at one instant, through the
    shipped steps in coherent mode: nothing is detected within a second of a glitch."""
    from so_transients.common import candidates
    from tests.conftest import load_group, run_sim, run_steps

    sim = run_sim(tmp_path, seed=13, observation={"duration": 300.0},
                  instrument={"bands": ["f090"]},
                  glitches={"enabled": True, "rate_per_hour": 600, "n_dets": [30, 60]})
    assert len(sim.glitches) >= 30
    aman = load_group(sim, band="f090")
    run_steps(aman, coherent_pipe())
    cands = candidates.from_aman(aman.transient_candidates, candidates.CAND_AXIS)
    t = cands["t_median"][np.asarray(cands["detected"], bool)]
    gap = np.min(np.abs(t[:, None] - np.asarray(sim.glitches["ctime"])[None, :]), axis=1,
                 initial=np.inf)
    assert np.all(gap > 1.0), gap


@pytest.mark.slow
@pytest.mark.parametrize("dead_mode", ["zeros", "nan"])
def test_coherent_mode_holds_on_imperfect_detectors(imperfect_bright_dataset, dead_mode):
    """16 % dead detectors (zeros or NaN), 2 % ten times noisier and cosmic-ray glitches,
    through the transient steps alone (no standard step cuts the bad detectors first): the
    3 Jy flare is detected, every candidate's Z is finite, and no dead detector is a hit."""
    from so_transients.common import candidates
    from tests.conftest import load_group, run_steps

    sim = imperfect_bright_dataset(dead_mode)
    aman = load_group(sim, band="f090")
    run_steps(aman, [s for s in coherent_pipe()
                     if s["name"] in candidates.STEPS or s["name"] == "transient_filter"])
    cands = candidates.from_aman(aman.transient_candidates, candidates.CAND_AXIS)
    assert len(cands["scan"]) and np.all(np.isfinite(cands["map_z"]))
    detected = np.asarray(cands["detected"], bool)
    t_flare = float(aman.timestamps[0]) + 120.0
    assert np.any(np.abs(cands["t_peak"][detected] - t_flare) < 2.0)
    dead = np.flatnonzero(np.asarray(aman.transient_filter.dead, bool))
    assert len(dead) >= 0.1 * aman.dets.count
    assert not np.isin(np.asarray(aman.transient_hits.det), dead).any()
