"""A versioned score model: its forest, its features, and how it was trained and measured.

The file is JSON (``format`` 1)::

    {"format": 1, "name": "real_score", "version": "...", "features": [...],
     "trained": {"config": ..., "seed": ..., "sklearn": ..., "commit": ..., "date": ...},
     "figures": {...},            # measured on held-out data (see docs/results/score.md)
     "trees": [...]}              # :mod:`.forest`

``transient_fit``'s ``score_model`` names such a file, or ``shipped`` for the one in the
package (:data:`SHIPPED`), made by ``so-transients study train-score``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from so_transients.score.features import feature_matrix
from so_transients.score.forest import Forest

FORMAT = 1
SHIPPED = Path(__file__).resolve().parent / "models" / "real_score.json"


@dataclass
class ScoreModel:
    features: list
    forest: Forest
    version: str
    trained: dict = field(default_factory=dict)
    figures: dict = field(default_factory=dict)
    name: str = "real_score"

    def score(self, cands) -> np.ndarray:
        """The probability that each candidate of ``cands`` (schema columns) is a real
        source: 0 (artefact) to 1."""
        n = len(np.asarray(cands["snr_max"]))
        if not n:
            return np.zeros(0)
        return self.forest.predict(feature_matrix(cands, self.features))

    def to_json(self) -> dict:
        return {"format": FORMAT, "name": self.name, "version": self.version,
                "features": list(self.features), "trained": self.trained,
                "figures": self.figures, "trees": self.forest.to_list()}

    def save(self, path):
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_json(), separators=(",", ":")) + "\n")
        return path


def model_path(name) -> Path:
    """The file of ``score_model`` ``name``: ``shipped`` or a path."""
    return SHIPPED if str(name) == "shipped" else Path(name).expanduser()


def load_model(name) -> ScoreModel:
    """The model ``name`` (``shipped`` or a path); errors name the file and what is wrong."""
    path = model_path(name)
    if not path.is_file():
        raise FileNotFoundError(f"score model {path}: no such file (train one with "
                                f"'so-transients study train-score')")
    try:
        d = json.loads(path.read_text())
        if d.get("format") != FORMAT:
            raise ValueError(f"format {d.get('format')!r}, this package reads {FORMAT}")
        return ScoreModel(list(d["features"]), Forest.from_list(d["trees"]), str(d["version"]),
                          d.get("trained", {}), d.get("figures", {}), d.get("name", "real_score"))
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"score model {path}: not a score model file ({exc})") from None
