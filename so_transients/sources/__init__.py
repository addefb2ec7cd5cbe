"""Catalogued sources: the known-source lists the cuts mask and the events cross-match,
read from SO's source catalogue (``socat``, by database URL) or from ECSV/CSV files, and the
cross-match of a position and flux against them.

- :mod:`.catalog`: a catalogue named by one string (socat URL or file) read into arrays, with
  every file checked (missing, empty, malformed, out of range) and errors naming the key
- :mod:`.crossmatch`: sotrplib's flux-dependent match radius, the nearest source, the ratio
  of measured to catalogued flux and the class of an event

Imports nothing but :mod:`so_transients.common`.
"""
