"""The paper's detection method (Clancy et al. 2025), as plain functions on arrays.

- :mod:`.matched_filter` and its compiled loops :mod:`.spectral_ops`: the per-detector
  matched filter (``transient_filter``); :mod:`.health`: how a group's detectors share the
  weight (effective number of detectors)
- :mod:`.find` and :mod:`.dbscan`: high-S/N samples clustered per scan (``transient_find``,
  paper mode)
- :mod:`.cuts`: is a candidate source-like (``transient_cuts``)
- :mod:`.fit`: the beam-model fit; :mod:`.error_scale`: its errors' measured scale, per scan
  direction; :mod:`.forced_fit`: the fit at a fixed position, over one or
  several crossings; :mod:`.fit_candidates`: a group's candidates fitted
  (``transient_fit``); :mod:`.motion`: detections whose position drifts
- :mod:`.cutout`: what a person vets a crossing with: a sky cutout made from the TOD and the
  time streams of the detectors that saw it

For the standard steps before the search, on real wafers: :mod:`.jumps` (readout jumps,
``transient_jumps``), :mod:`.common_mode` (a wafer's common mode; crossings hidden from the
PCA, ``transient_pca_mask``) and :mod:`.pca` (sotodlib's PCA filter in blocks of samples,
``transient_pca_filter``).

Imports only from :mod:`so_transients.common`.
"""
