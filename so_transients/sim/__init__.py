"""The SO LAT observation simulator: observations written as a dataset sotodlib's Context opens.

- :mod:`.config`: the simulation YAML read into validated dataclasses
- :mod:`.focal_plane`: tubes, hexagonal wafers and dichroic pixels (MF: f090/f150, UHF:
  f220/f280)
- :mod:`.scan`: constant-elevation azimuth scans with finite-acceleration turnarounds
- :mod:`.atmosphere`, :mod:`.cmb`: the sky and atmosphere every detector sees
- :mod:`.sources`: flares and steady point sources; :mod:`.moving`: planet-like sources
- :mod:`.glitches`, :mod:`.jumps`, :mod:`.imperfections`: what makes real detectors differ
  from ideal ones
- :mod:`.simulate`: one wafer-band group at a time; :mod:`.dataset`: the dataset on disk
- :mod:`.command`: ``so-transients simulate``

Uses :mod:`so_transients.common` and :mod:`so_transients.io`, never the search.
"""
