"""The score model: its features from candidate columns, its file, and what goes wrong named."""
import json

import numpy as np
import pytest

from so_transients.common import candidates
from so_transients.score.features import FEATURES, MISSING, feature_matrix
from so_transients.score.model import SHIPPED, load_model
from so_transients.score.training import rejection, threshold_at_recall, train_model


def _cands(n, rng, glitch):
    """Candidate columns: a source crossing drifts (hit times spread along the scan, the fit
    explains the brightest detector), a cosmic ray hits its detectors at one instant with one
    detector far above the fit."""
    c = {k: np.full(n, v, float) for k, v in
         {"n_fit_dets": 60, "pol_fraction": 0.5, "offset": 0.0, "offset_err": 1.0,
          "t_start": 0.0, "aspect_ratio": 4.0}.items()}
    snr_fit = rng.uniform(5, 30, n)
    c["snr_fit"] = snr_fit
    c["snr_max"] = snr_fit * (rng.uniform(3, 8, n) if glitch else rng.uniform(0.3, 0.6, n))
    c["n_dets"] = rng.integers(3, 8, n) if glitch else rng.integers(10, 40, n)
    c["n_samples"] = c["n_dets"] * (rng.integers(1, 3, n) if glitch else rng.integers(5, 20, n))
    c["time_rms"] = rng.uniform(0.2, 0.5, n) if glitch else rng.uniform(0.01, 0.05, n)
    c["instant_rms"] = rng.uniform(0.0, 0.01, n) if glitch else rng.uniform(0.1, 0.3, n)
    c["opposite_snr"] = -rng.uniform(0, 1, n) * c["snr_max"]
    c["chi2_red"] = rng.uniform(2, 6, n) if glitch else rng.uniform(0.9, 1.3, n)
    c["t_stop"] = rng.uniform(0.0, 0.05, n) if glitch else rng.uniform(0.3, 1.5, n)
    return c


def _join(a, b):
    return {k: np.concatenate([a[k], b[k]]) for k in a}


def test_every_feature_is_computed_from_schema_columns():
    rng = np.random.default_rng(0)
    c = _cands(5, rng, glitch=False)
    X = feature_matrix(c)
    assert X.shape == (5, len(FEATURES)) and np.isfinite(X).all()
    used = {"snr_max", "snr_fit", "n_dets", "n_samples", "n_fit_dets", "aspect_ratio",
            "time_rms", "instant_rms", "opposite_snr", "pol_fraction", "chi2_red", "offset",
            "offset_err", "t_start", "t_stop"}
    assert used <= set(candidates.BY_NAME)


def test_a_missing_value_is_set_apart_and_an_unknown_feature_named():
    c = _cands(3, np.random.default_rng(1), glitch=False)
    c["chi2_red"][1] = np.nan
    del c["pol_fraction"]                          # a step that did not run
    X = feature_matrix(c, ["chi2_red", "pol_fraction"])
    assert X[1, 0] == MISSING and (X[:, 1] == MISSING).all() and X[0, 0] != MISSING
    with pytest.raises(KeyError, match="brightness"):
        feature_matrix(c, ["brightness"])


def test_a_glitch_like_candidate_is_scored_as_artefact(tmp_path):
    rng = np.random.default_rng(2)
    train = _join(_cands(300, rng, glitch=False), _cands(300, rng, glitch=True))
    labels = np.r_[np.ones(300), np.zeros(300)]
    model = train_model(train, labels, seed=0, version="test",
                        n_trees=30, max_depth=5, min_samples_leaf=3)
    back = load_model(model.save(tmp_path / "m.json"))
    sources, glitches = _cands(100, rng, glitch=False), _cands(100, rng, glitch=True)
    s_real, s_glitch = back.score(sources), back.score(glitches)
    assert np.median(s_glitch) < 0.1 < 0.9 < np.median(s_real)
    res = rejection(s_real, s_glitch, recalls=(0.99,))["0.99"]
    assert res["recall"] >= 0.99 and res["rejected"] > 0.9
    assert back.trained["n_real"] == 300 and back.trained["seed"] == 0


def test_training_refuses_one_class():
    c = _cands(10, np.random.default_rng(3), glitch=False)
    with pytest.raises(ValueError, match="both real and artefact"):
        train_model(c, np.ones(10), seed=0, version="x")


def test_the_cut_at_a_recall_keeps_at_least_that_share():
    rng = np.random.default_rng(4)
    for n in (1, 7, 100, 1001):
        s = rng.uniform(size=n)
        for r in (0.5, 0.9, 0.99, 0.999):
            cut = threshold_at_recall(s, r)
            assert np.mean(s >= cut) >= r
            # and the next real score up would lose too many
            higher = s[s > cut]
            if len(higher):
                assert np.mean(s >= higher.min()) < r


def test_a_bad_model_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.json"):
        load_model(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": 99}))
    with pytest.raises(ValueError, match="bad.json.*format 99"):
        load_model(bad)



def test_the_shipped_model_reads_and_scores():
    model = load_model("shipped")
    assert SHIPPED.is_file() and model.trained.get("config") and model.figures
    c = _cands(4, np.random.default_rng(5), glitch=False)
    s = model.score(c)
    assert s.shape == (4,) and ((0 <= s) & (s <= 1)).all()
