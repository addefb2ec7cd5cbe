"""Injection-recovery campaigns (``so-transients study campaign CONFIG``): flares of known peak flux
and rise time injected into simulated noise-only observations, searched with the site config's
transient steps, matched to the truth, and summarized as the reference paper does (detection
thresholds, flux and pointing recovery, false positives). See :mod:`.run` for the layout of a
campaign folder and :mod:`.flare_injection` for the fast injection path.

- :mod:`.config`, :mod:`.run`, :mod:`.work_units`, :mod:`.noise`: the campaign and its units
- :mod:`.noise_model`, :mod:`.pca_response`, :mod:`.flare_injection`: the fast injection path
  (the filter's noise model, what the PCA takes of a flare, the injection); :mod:`.full_check`:
  the same flares through the full site pipeline
- :mod:`.search_steps`: the site config's search steps run in-process
- :mod:`.matching`: detections matched to injected flares
- :mod:`.stats`, :mod:`.report`, :mod:`.markdown`, :mod:`.figures`, :mod:`.combine`: results
- :mod:`.equal_rate`, :mod:`.far_budget`: thresholds at the paper's false-detection rate;
  :mod:`.far_tables`: the false-alarm studies' tables as their results page shows them;
  :mod:`.mode_tables`: both search modes' grids side by side at the paper's rate
- :mod:`.events_check`: the events step measured on simulated flares
- :mod:`.score_training`: the real-or-artefact score trained on simulated real wafers
- :mod:`.command`: ``so-transients study`` and its studies
- :mod:`.drawn_wafer`, :mod:`.real_wafer`, :mod:`.real_wafer_tables`: realization studies on
  simulated real wafers and their results page's tables;
  :mod:`.provenance`: the commit and day a study's table records
"""
