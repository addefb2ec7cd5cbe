"""What every part of the package shares, and nothing of sotodlib's pipeline.

- :mod:`.angles`: angle units and great-circle distances
- :mod:`.bands`: the SO LAT bands and their beams
- :mod:`.robust`: robust scatter
- :mod:`.pointing`: exact pointing of chosen samples with so3g quaternions
- :mod:`.scan_geometry`: sample rate, scan speed, drift and detector pitch from standard fields
- :mod:`.flare_model`: the flare light curve of Clancy et al. (2025), eq. 1
- :mod:`.candidates`: the candidate schema every step, table and campaign shares
- :mod:`.step_config`: a step's YAML block read into its config dataclass, checked
- :mod:`.parallel`: independent work dispatched through sotodlib's executor
- :mod:`.tables`: tables read back as written (ECSV, FITS, CSV)
- :mod:`.times`: ctime or ISO UTC as users give them
- :mod:`.sky_match`: positions matched on the sky (astropy's k-d tree)

Imports nothing from the other subpackages.
"""
