"""sotodlib's site pipeline with the transient steps, and its results read back.

- :mod:`.pipeline`: site configs written, checked and run on a dataset; failed groups
- :mod:`.run`: ``python -m so_transients.site.run``: ``preprocess_tod`` with its pool shut down
- :mod:`.results`: one astropy table of candidates from an archive or an observation
- :mod:`.provenance`: where a results table comes from
- :mod:`.summary`: a plain-text summary of a dataset
- :mod:`.losses`: what each group lost (detectors removed and why, samples masked)
- :mod:`.turnarounds`: observations too short for a config's turnaround flags
- commands (``get_parser``, ``main``): :mod:`.config_command` (``site-config``),
  :mod:`.run_command` (``run``), :mod:`.catalog_command` (``catalog``),
  :mod:`.summary_command` (``summary``), :mod:`.schema_command` (``schema``)
"""
