"""From detections to astrophysical events: association, forced photometry, light curves
(``so-transients events``, :mod:`so_transients.events.command`).

- :mod:`.association`: detections joined into events, events into sources
- :mod:`.group_photometry`: forced photometry of every event in one group
- :mod:`.lightcurve_fit`: eq. 1 of Clancy et al. (2025) per band, and the spectral index
- :mod:`.schema`, :mod:`.tables`: the event tables' columns, and the tables built
- :mod:`.cutouts`: each event's sky cutouts and detector time streams, written out
- :mod:`.injections`: events matched to a simulation's injected flares
- :mod:`.config`, :mod:`.command`, :mod:`.figures`: the command, its YAML and its figures
"""
