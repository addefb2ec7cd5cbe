"""The vetting site a person reads: every event, its light curve, detectors and sky cutout,
with labels to give (``so-transients report``, :mod:`so_transients.report.command`).

- :mod:`.pages`: the site of an events folder (index and event pages, from jinja2 templates)
- :mod:`.plots`: an event's cutout and time-stream figures
- ``templates/``: the pages' templates, stylesheet and script (no network)
"""
