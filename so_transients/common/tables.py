"""Tables written and read back alike in ECSV, FITS and CSV.

astropy reads an empty string back as a masked value in all three formats (and NaN as
masked in FITS, and ``True``/``False`` as strings in CSV), so a column such as ``cut_reason``
(``''``: no cut failed) would come back masked where it was written empty. Two helpers keep
what was written:

* :func:`for_writing` prepares a table for a format: in ECSV, string columns are written with
  their (empty) mask, so that any ``Table.read`` gives ``''`` back, not a masked value;
* :func:`read_table` reads any of the three formats with empty strings as ``''`` (plain
  ``str`` columns), NaN as NaN and booleans as booleans: the package's readers use it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.io import ascii
from astropy.table import MaskedColumn, Table

#: astropy formats of the tables the package writes, by file suffix.
FORMATS = {".ecsv": "ascii.ecsv", ".fits": "fits", ".fit": "fits", ".csv": "ascii.csv"}

#: CSV cells tried as int, float, bool, then str (astropy's default leaves out bool).
CSV_CONVERTERS = {"*": [ascii.convert_numpy(t) for t in (int, float, bool, str)]}


def format_of(path) -> str | None:
    """The astropy format of ``path`` by its suffix (None: not one of :data:`FORMATS`)."""
    return FORMATS.get(Path(path).suffix.lower())


def for_writing(table: Table, fmt) -> tuple[Table, dict]:
    """``(table, options)`` to write ``table`` in astropy format ``fmt`` so that empty
    strings read back as ``''``: in ECSV each string column is written as a column with a
    mask (none of it masked), which astropy's ECSV reader takes as the data itself, ``''``
    included; other formats are returned as they are (read them with :func:`read_table`)."""
    if fmt != "ascii.ecsv":
        return table, {}
    out = table.copy(copy_data=False)
    names = [n for n in out.colnames if out[n].dtype.kind in "US" and out[n].ndim == 1]
    for name in names:
        col = out[name]
        mask = col.mask if isinstance(col, MaskedColumn) else np.zeros(len(col), bool)
        out[name] = MaskedColumn(col.filled("") if isinstance(col, MaskedColumn) else col,
                                 mask=mask, copy=False)
    return out, {"serialize_method": {n: "data_mask" for n in names}} if names else {}


def plain_columns(table: Table) -> Table:
    """``table`` (changed in place and returned) with bytes decoded to ``str``, masked
    strings as ``''``, masked floats as NaN, and other masked columns plain where nothing
    of them is masked (an int or bool column with masked entries stays masked)."""
    table.convert_bytestring_to_unicode()
    for name in table.colnames:
        col = table[name]
        if not isinstance(col, MaskedColumn):
            continue
        kind = col.dtype.kind
        if kind == "U":
            table[name] = col.filled("")
        elif kind == "f":
            table[name] = col.filled(np.nan)
        elif not np.any(col.mask):
            table[name] = col.filled()
    return table


def read_table(path, format=None, **kwargs) -> Table:
    """``Table.read`` of an ECSV, FITS or CSV file (format from the suffix unless given),
    with the values the writer had: empty strings as ``''`` in plain ``str`` columns, NaN as
    NaN, booleans as booleans (CSV: ``True``/``False`` cells; ``#`` lines are comments, the
    provenance lines written by :func:`so_transients.site.results.write_table`)."""
    fmt = format or format_of(path)
    if fmt == "ascii.csv":
        kwargs = {"comment": "#", "converters": CSV_CONVERTERS, **kwargs}
    try:
        table = Table.read(path, format=fmt, **kwargs) if fmt else Table.read(path, **kwargs)
    except ValueError as exc:        # astropy's messages do not name the file
        raise ValueError(f"{path}: cannot read it as a table ({fmt or 'format by astropy'}): "
                         f"{exc}") from exc
    return plain_columns(table)
