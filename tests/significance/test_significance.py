"""transient_significance: a far for every candidate, in the site pipeline and the archive."""
import logging

import numpy as np
import pytest
import yaml
from astropy.table import Table

from so_transients.coherent.config import CoherentConfig
from so_transients.common import candidates
from so_transients.site.results import archive_table
from so_transients.site.pipeline import (
    PAPER, failed_groups, run_site_pipeline, write_site_config
)

from tests.conftest import load_group, run_steps

STEP = {"name": "transient_significance", "calc": {"n_slides": 10}, "save": True}


def with_significance(process_pipe, **calc):
    """``process_pipe`` with transient_significance before transient_fit."""
    steps = [dict(s) for s in process_pipe]
    k = [s["name"] for s in steps].index("transient_fit")
    steps.insert(k, {**STEP, "calc": {**STEP["calc"], **calc}})
    return steps


@pytest.fixture(scope="module")
def significance_run(module_tmp, two_flare_dataset):
    """Five minutes of w16 at f090, two bright flares; the site pipeline with the step."""
    root = module_tmp("significance")
    sim = two_flare_dataset
    config = write_site_config(sim.context.parent, path=root / "preprocess.yaml",
                               results=root / "preprocess", template=PAPER)
    cfg = yaml.safe_load(config.read_text())
    cfg["process_pipe"] = with_significance(cfg["process_pipe"])
    config.write_text(yaml.safe_dump(cfg, sort_keys=False))
    run_site_pipeline(config)
    return sim, config


@pytest.mark.slow
def test_every_candidate_gets_a_far_in_the_archive(significance_run):
    _, config = significance_run
    assert failed_groups(config) == ""
    table = archive_table(config, detected_only=False)
    assert {"coherent_snr", "far", "pass_far"} <= set(table.colnames)
    assert table["far"].unit == "1 / h"
    fitted = np.isfinite(table["coherent_snr"])
    assert fitted.mean() > 0.9
    detected = table[np.asarray(table["detected"], bool)]
    assert len(detected) >= 2
    # bright flares: beyond every background maximum of 10 slides of 5 minutes, so their
    # far is the bound (half a false alarm in the background's live time)
    assert np.all(detected["coherent_snr"] > 8)
    assert np.all(detected["far"] <= np.nanmin(table["far"]) * 1.0001)
    # far falls as Z rises
    order = np.argsort(np.asarray(table["coherent_snr"])[fitted])
    assert np.all(np.diff(np.asarray(table["far"])[fitted][order]) <= 1e-12)


@pytest.mark.slow
def test_max_far_cuts_and_a_background_too_short_is_named(significance_run, caplog):
    sim, config = significance_run
    aman = load_group(sim, band="f090")
    pipe = yaml.safe_load(config.read_text())["process_pipe"]
    steps = with_significance([s for s in pipe if s["name"] != STEP["name"]], max_far=1e-3)
    with caplog.at_level(logging.WARNING):
        run_steps(aman, steps)
    cands = candidates.from_aman(aman.transient_candidates, candidates.CAND_AXIS)
    assert not np.any(cands["pass_far"]) and not np.any(cands["detected"])
    assert any("cannot resolve max_far" in r.message and sim.obs_ids[0] in r.message
               for r in caplog.records)


@pytest.mark.slow
def test_without_slides_far_rests_on_the_inverted_data(significance_run, caplog):
    """``n_slides: 0`` (what a paper-mode campaign runs in its windows): the same coherent_snr
    as with slides, far from the sign-inverted data alone, and no warning about slides."""
    sim, config = significance_run
    with_slides = archive_table(config, detected_only=False)
    aman = load_group(sim, band="f090")
    pipe = yaml.safe_load(config.read_text())["process_pipe"]
    with caplog.at_level(logging.WARNING):
        run_steps(aman, with_significance([s for s in pipe if s["name"] != STEP["name"]],
                                          n_slides=0))
    cands = candidates.from_aman(aman.transient_candidates, candidates.CAND_AXIS)
    ours = np.asarray(cands["coherent_snr"])[np.argsort(cands["cand_id"])]
    theirs = np.asarray(with_slides["coherent_snr"])[np.argsort(with_slides["cand_id"])]
    assert len(ours) == len(theirs) and np.allclose(ours, theirs, equal_nan=True)
    assert np.all(np.isnan(cands["far_slides"]))
    finite = np.isfinite(cands["coherent_snr"])
    assert finite.any() and np.array_equal(cands["far"][finite], cands["far_inverted"][finite])
    assert not [r for r in caplog.records if "slides" in r.message]


def test_without_the_step_candidates_pass_far(tmp_path):
    rows = candidates.table({"cand_id": np.array([0]), "bandpass": np.array(["f090"])})
    assert bool(rows["pass_far"][0]) and np.isnan(rows["far"][0])
    assert isinstance(rows, Table)


@pytest.mark.slow
@pytest.mark.parametrize("dead_mode", ["zeros", "nan"])
def test_imperfect_detectors_keep_a_bright_flare_significant(imperfect_bright_dataset,
                                                            dead_mode):
    """16 % dead detectors (all zeros, or all NaN), 2 % ten times noisier, and cosmic-ray
    glitches, through the transient steps alone (none of the standard steps that would cut
    bad detectors first) with significance: the bright flare is detected with a finite Z
    beyond every background maximum, and the Z scale stays finite."""
    sim = imperfect_bright_dataset(dead_mode)
    pipe = yaml.safe_load(PAPER.read_text())["process_pipe"]
    aman = load_group(sim, band="f090")
    run_steps(aman, with_significance([s for s in pipe if s["name"] in candidates.STEPS
                                       or s["name"] == "transient_filter"]))
    cands = candidates.from_aman(aman.transient_candidates, candidates.CAND_AXIS)
    found = np.flatnonzero(np.asarray(cands["detected"], bool))
    t_flare = float(aman.timestamps[0]) + 120.0
    at_flare = found[np.abs(cands["t_peak"][found] - t_flare) < 2.0]
    others = np.setdiff1d(found, at_flare)
    assert len(at_flare) >= 1
    z, far = cands["coherent_snr"][at_flare], cands["far"][at_flare]
    assert np.all(np.isfinite(z)) and np.all(z > 8)
    assert np.all(far <= np.nanmin(cands["far"]) * 1.0001)      # beyond every maximum
    # any other detection (noise or a glitch residue: the shipped config has no peak-ratio
    # cut) ranks below the flare: a smaller Z and a higher far
    assert np.all(cands["coherent_snr"][others] < z.min())
    assert np.all(cands["far"][others] > far.max())
    assert np.isfinite(float(aman.transient_candidates.significance_z_scale))


def test_the_inverted_rate_counts_then_follows_the_tail_model():
    from so_transients.significance.far import inverted_rate
    from so_transients.significance.tail_model import model_count_above

    rng = np.random.default_rng(8)
    # maxima of unit-variance noise above 3: the tail of a Gaussian (drawn by rejection)
    draws = rng.normal(size=4_000_000)
    maxima = draws[draws >= 3.0]
    hours = 2.0
    rate = inverted_rate([3.2, 4.0, 6.0], maxima, hours, 3.5)
    # below tail_from: the count; beyond it, the higher of the count and the model
    assert rate[0] == np.sum(maxima >= 3.2) / hours
    assert rate[1] == max(np.sum(maxima >= 4.0), model_count_above(4.0, maxima, 3.5)) / hours
    # far beyond every maximum the count is 0 but the model still resolves a rate, close
    # to the Gaussian's: N(>6) / N(>3.5) = 4.2e-6 (the model's exp(-(x^2 - x0^2)/2) form
    # leaves out the 1/x factor: about x0 / x = 0.6 of it)
    n35 = np.sum(maxima >= 3.5)
    assert 0 < rate[2] * hours < n35 * 4.2e-6 * 1.0 and rate[2] * hours > n35 * 4.2e-6 * 0.3
    assert np.all(np.isnan(inverted_rate([4.0], maxima, 0.0, 3.5)))


def test_a_bright_sources_filter_sidelobes_are_not_inverted_background():
    from so_transients.coherent.statistic import row_offsets
    from so_transients.significance.far import inverted_maxima, SignificanceConfig
    from so_transients.coherent.statistic import coherent_map

    from tests.coherent.test_coherent import SIGMA_BEAM, inject, wafer

    rng = np.random.default_rng(9)
    geometry, sigma = wafer(rng=rng)
    snr = rng.normal(size=(len(sigma), 4000))
    rows = row_offsets(geometry, SIGMA_BEAM, 0.8)
    c = rows[len(rows) // 2]
    inject(snr, geometry, sigma, 600.0, 2000, c)               # Z about 100
    for lobe in (-12, 12):                                     # the filter's negative lobes
        inject(snr, geometry, sigma, -0.3 * 600.0, 2000 + lobe, c)
    live = np.ones(len(sigma), bool)
    z, _ = coherent_map(snr, geometry, rows, SIGMA_BEAM, sigma, live)

    def near_source(cfg):
        out, _ = inverted_maxima(z, snr, geometry, rows, SIGMA_BEAM, sigma, live, 1.0, 3, cfg,
                                 CoherentConfig().vetoes)
        return np.sum(out >= 10)                                # far above the noise

    assert near_source(SignificanceConfig()) == 0
    assert near_source(SignificanceConfig(max_opposite_ratio=1e9)) > 0


def test_slides_follow_max_far_when_n_slides_is_null():
    from so_transients.common.step_config import ConfigError
    from so_transients.significance.far import SignificanceConfig

    cfg = SignificanceConfig(n_slides=None, max_far=0.005)
    # 0.55 / max_far = 110 h of slides: 10 minutes searched need 660, an hour 110
    assert cfg.slides_for(600 / 3600) == 660
    assert cfg.slides_for(1.0) == 110
    assert cfg.slides_for(10.0) == 100                  # never fewer than 100
    # a candidate above every slide maximum then passes max_far: 0.5 / live < max_far
    assert 0.5 / (cfg.slides_for(0.137) * 0.137) < cfg.max_far
    assert SignificanceConfig(n_slides=7, max_far=0.005).slides_for(1.0) == 7
    with pytest.raises(ConfigError, match="requires max_far"):
        SignificanceConfig(n_slides=None)


def test_a_far_at_the_slides_resolution_is_marked_as_a_bound():
    from so_transients.significance.far import far_is_limit
    hours = 110.0
    far_slides = np.array([0.5 / hours, 1 / hours, 0.5 / hours, np.nan, 0.5 / hours])
    far = np.array([0.5 / hours, 1 / hours, 3 / hours, np.nan, 0.5 / hours])
    # no slide above; one above; the inverted data count more; no far; ... on no slides
    assert list(far_is_limit(far, far_slides, hours)) == [True, False, False, False, True]
    assert not far_is_limit(far, far_slides, 0.0).any()
