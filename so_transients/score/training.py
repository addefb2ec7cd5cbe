"""Labelled candidates to a score model, and how well a score separates them.

Training needs scikit-learn (a ``RandomForestClassifier``); using a model does not
(:mod:`.forest`). Labels: 1 for a candidate an injected flare explains, 0 for one nothing
does; :mod:`so_transients.campaign.score_training` makes them.
"""
from __future__ import annotations

import numpy as np

from so_transients.score.features import FEATURES, feature_matrix
from so_transients.score.forest import from_sklearn
from so_transients.score.model import ScoreModel


def fit_forest(X, y, seed, n_trees=100, max_depth=8, min_samples_leaf=5):
    """A random forest on features ``X`` and labels ``y`` (0/1), classes weighted so that the
    few real candidates count as much as the many artefacts."""
    from sklearn.ensemble import RandomForestClassifier

    model = RandomForestClassifier(n_estimators=n_trees, max_depth=max_depth,
                                   min_samples_leaf=min_samples_leaf,
                                   class_weight="balanced_subsample", random_state=seed,
                                   n_jobs=1)
    model.fit(np.asarray(X, float), np.asarray(y, int))
    return model


def train_model(cands, labels, seed, version, trained=None, features=None, **forest_options):
    """A :class:`ScoreModel` trained on the candidates ``cands`` (schema columns) with 0/1
    ``labels``; ``trained``: what to record of the training (config, seeds, ...)."""
    features = list(FEATURES) if features is None else list(features)
    labels = np.asarray(labels, int)
    if labels.min(initial=1) > 0 or labels.max(initial=0) < 1:
        raise ValueError(f"training needs both real and artefact candidates; got "
                         f"{int(labels.sum())} real of {len(labels)}")
    sk = fit_forest(feature_matrix(cands, features), labels, seed, **forest_options)
    import sklearn

    record = {**(trained or {}), "seed": seed, "sklearn": sklearn.__version__,
              "n_real": int(labels.sum()), "n_artefact": int((labels == 0).sum()),
              "forest": {"n_trees": sk.n_estimators, "max_depth": sk.max_depth,
                         "min_samples_leaf": sk.min_samples_leaf}}
    return ScoreModel(features, from_sklearn(sk), version, record)


def threshold_at_recall(real_scores, recall) -> float:
    """The highest cut on the score that keeps at least ``recall`` of ``real_scores``."""
    s = np.sort(np.asarray(real_scores, float))
    if not len(s):
        return np.nan
    lost = int(np.floor((1.0 - recall) * len(s) + 1e-9))   # real candidates allowed below
    return float(s[lost])


def rejection(real_scores, false_scores, recalls=(0.99, 0.999)) -> dict:
    """Per recall: the cut keeping that share of the real candidates, the share of real ones
    it keeps and of false ones it rejects (with counts)."""
    real, false = np.asarray(real_scores, float), np.asarray(false_scores, float)
    out = {}
    for r in recalls:
        cut = threshold_at_recall(real, r)
        out[f"{r:g}"] = {"cut": cut, "recall": float(np.mean(real >= cut)) if len(real) else np.nan,
                         "rejected": float(np.mean(false < cut)) if len(false) else np.nan,
                         "n_real": int(len(real)), "n_false": int(len(false))}
    return out
