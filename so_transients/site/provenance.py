"""Where a results table comes from: the software versions, the preprocess config (path and
a digest of its content), the observations and the time it was written.

Written into every table's metadata by :func:`so_transients.site.results.write_table`: as a
``provenance`` mapping in ECSV, as header keywords in FITS (:data:`FITS_KEYS`), as comment
lines in CSV.
"""
from __future__ import annotations

import hashlib
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

#: FITS header keyword of each provenance entry (8 characters at most).
FITS_KEYS = {"so_transients_version": "SOTRVER", "sotodlib_version": "SOTODVER",
             "so3g_version": "SO3GVER", "preprocess_config": "PPCONFIG",
             "preprocess_config_sha256": "PPSHA256", "obs_ids": "OBSIDS",
             "created_utc": "DATE"}


def package_version(name) -> str:
    """The installed version of distribution ``name``, 'unknown' when not installed."""
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "unknown"


def file_digest(path) -> str:
    """SHA-256 of a file's bytes, in hex."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def provenance(config=None, obs_ids=()) -> dict:
    """The provenance block of a table made with preprocess config ``config`` (a path, or
    None when unknown) from observations ``obs_ids``."""
    config = Path(config).resolve() if config else None
    return {
        "so_transients_version": package_version("so_transients"),
        "sotodlib_version": package_version("sotodlib"),
        "so3g_version": package_version("so3g"),
        "preprocess_config": str(config) if config else "",
        "preprocess_config_sha256": file_digest(config) if config and config.is_file() else "",
        "obs_ids": sorted({str(o) for o in obs_ids}),
        "created_utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S"),
    }


def fits_header(prov: dict) -> dict:
    """``prov`` as FITS header keywords: lists joined with commas."""
    return {FITS_KEYS[k]: ",".join(v) if isinstance(v, list) else v for k, v in prov.items()}


def comment_lines(prov: dict) -> list:
    """``prov`` as ``key: value`` lines (CSV comments)."""
    return [f"{k}: {','.join(v) if isinstance(v, list) else v}" for k, v in prov.items()]


def attach(table, fmt, prov: dict):
    """Put ``prov`` in ``table``'s metadata as format ``fmt`` (astropy's name) carries it:
    header keywords in FITS, ``# key: value`` comment lines in CSV, a ``provenance`` mapping
    otherwise (ECSV). Returns the table."""
    if fmt == "fits":
        table.meta.update(fits_header(prov))
    elif fmt == "ascii.csv":
        table.meta["comments"] = comment_lines(prov)
    else:
        table.meta["provenance"] = prov
    return table
