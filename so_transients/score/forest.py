"""A random forest held as plain arrays: read from and written to JSON, evaluated with numpy.

A model file must outlive the scikit-learn version that trained it and say what is in it, so
the trees are stored as their node arrays (feature, threshold, children, leaf probability), not
as a pickle. :func:`from_sklearn` copies them out of a fitted
``sklearn.ensemble.RandomForestClassifier``; :meth:`Forest.predict` gives the same
probabilities as its ``predict_proba(X)[:, 1]`` (a test holds it to that).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Tree:
    feature: np.ndarray      # (n_nodes,) feature split on; -1 at a leaf
    threshold: np.ndarray    # go left where x[feature] <= threshold
    left: np.ndarray
    right: np.ndarray
    prob: np.ndarray         # probability of the positive class at each node

    def predict(self, X) -> np.ndarray:
        node = np.zeros(len(X), np.int64)
        rows = np.arange(len(X))
        while True:
            inner = self.feature[node] >= 0
            if not inner.any():
                return self.prob[node]
            i = rows[inner]
            n = node[inner]
            go_left = X[i, self.feature[n]] <= self.threshold[n]
            node[inner] = np.where(go_left, self.left[n], self.right[n])

    def to_dict(self) -> dict:
        return {"feature": self.feature.tolist(), "threshold": self.threshold.tolist(),
                "left": self.left.tolist(), "right": self.right.tolist(),
                "prob": np.round(self.prob, 6).tolist()}

    @classmethod
    def from_dict(cls, d) -> "Tree":
        return cls(np.asarray(d["feature"], np.int64), np.asarray(d["threshold"], float),
                   np.asarray(d["left"], np.int64), np.asarray(d["right"], np.int64),
                   np.asarray(d["prob"], float))


@dataclass
class Forest:
    trees: list

    def predict(self, X) -> np.ndarray:
        """Mean over the trees of the positive class's probability, for each row of ``X``."""
        X = np.asarray(X, float)
        if not len(X):
            return np.zeros(0)
        return np.mean([t.predict(X) for t in self.trees], axis=0)

    def to_list(self) -> list:
        return [t.to_dict() for t in self.trees]

    @classmethod
    def from_list(cls, trees) -> "Forest":
        return cls([Tree.from_dict(t) for t in trees])


def from_sklearn(model) -> Forest:
    """The trees of a fitted two-class ``RandomForestClassifier`` (classes 0 and 1)."""
    if list(model.classes_) != [0, 1]:
        raise ValueError(f"expected classes [0, 1], got {list(model.classes_)}")
    trees = []
    for est in model.estimators_:
        t = est.tree_
        value = t.value[:, 0, :]
        prob = value[:, 1] / value.sum(axis=1)
        leaf = t.children_left < 0
        trees.append(Tree(np.where(leaf, -1, t.feature).astype(np.int64),
                          t.threshold.astype(float), t.children_left.astype(np.int64),
                          t.children_right.astype(np.int64), prob))
    return Forest(trees)
