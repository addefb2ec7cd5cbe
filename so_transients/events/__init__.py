"""From detections to astrophysical events: association, forced photometry, light curves
(``so-transients events``, :mod:`so_transients.events.command`)."""
