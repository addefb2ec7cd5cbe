"""A learned real-or-artefact score for candidates (``transient_fit``'s ``score_model``).

- :mod:`.features`: the score's inputs, computed from a candidate's schema columns
- :mod:`.forest`: a random forest held as plain arrays (read from and written to JSON,
  evaluated with numpy; scikit-learn is needed only to train one)
- :mod:`.model`: a versioned score model: its forest, features, and the config, seed and
  measured figures it was trained with; the shipped model
- :mod:`.training`: labelled candidates to a model, and its rejection at a given recall

Imports only from :mod:`so_transients.common`. The candidates it learns from are made by
:mod:`so_transients.campaign.score_training` (``so-transients study train-score``).
"""
