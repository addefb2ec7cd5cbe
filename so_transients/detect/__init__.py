"""The paper's detection method (Clancy et al. 2025), as plain functions on arrays.

- :mod:`.matched_filter` and its compiled loops :mod:`.spectral_ops`: the per-detector
  matched filter (``transient_filter``)
- :mod:`.find` and :mod:`.dbscan`: high-S/N samples clustered per scan (``transient_find``,
  paper mode)
- :mod:`.cuts`: is a candidate source-like (``transient_cuts``)
- :mod:`.fit`: the beam-model fit; :mod:`.forced_fit`: the fit at a fixed position, over one or
  several crossings; :mod:`.fit_candidates`: a group's candidates fitted
  (``transient_fit``); :mod:`.motion`: detections whose position drifts

Imports only from :mod:`so_transients.common`.
"""
