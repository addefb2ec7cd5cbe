"""The forest held as arrays gives scikit-learn's probabilities, and survives its JSON file."""
import json

import numpy as np
from sklearn.ensemble import RandomForestClassifier

from so_transients.score.forest import Forest, from_sklearn


def _fitted(seed=3):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(600, 5))
    y = (X[:, 0] + 0.5 * X[:, 1] ** 2 + rng.normal(0, 0.5, 600) > 0.8).astype(int)
    model = RandomForestClassifier(n_estimators=20, max_depth=6, random_state=seed).fit(X, y)
    return model, rng.normal(size=(300, 5))


def test_the_arrays_give_sklearns_probabilities():
    model, X = _fitted()
    np.testing.assert_allclose(from_sklearn(model).predict(X), model.predict_proba(X)[:, 1],
                               atol=1e-12)


def test_the_json_round_trip_keeps_every_score():
    model, X = _fitted()
    forest = from_sklearn(model)
    back = Forest.from_list(json.loads(json.dumps(forest.to_list())))
    # leaf probabilities are stored to 6 decimals
    np.testing.assert_allclose(back.predict(X), forest.predict(X), atol=1e-6)


def test_no_rows_no_scores():
    model, _ = _fitted()
    assert from_sklearn(model).predict(np.zeros((0, 5))).shape == (0,)
