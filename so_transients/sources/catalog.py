"""Known sources as arrays: from SO's source catalogue (``socat``) by database URL, or from an
ECSV/CSV file.

A catalogue is named by one string, the ``catalogue`` / ``known_sources`` config value:

* ``socat:`` -- the socat database its own settings name (environment variables with the
  ``socat_model_`` prefix: ``socat_model_database_type`` sqlite or postgresql,
  ``socat_model_database_name`` the file or the server);
* ``socat:///path/socat.db`` -- a socat SQLite file;
* an SQLAlchemy URL of a socat database: ``sqlite:///path/socat.db``,
  ``postgresql://user@host/db`` (socat's schema: ``fixed_sources``, ``solarsystem_objects``,
  ``moving_sources``);
* anything else is a file: ECSV (``.ecsv``) or CSV with ``ra`` and ``dec`` columns (degrees
  unless the column carries a unit) and optionally ``name``, ``source_id`` and ``flux`` (mJy
  unless the column carries a unit).

socat is an optional dependency (``pip install so_transients[catalog]``); it is imported only
when a socat URL is read. Both socat's released API (0.0.2: integer ids, ``Client.get_box``,
ephemeris times in ctime) and its current one (0.1: UUIDs, ``Client.get_box_fixed``, ephemeris
times as datetimes) are read. Fixed sources are read with socat's DB client over the whole
sky; the ephemeris points of its solar-system objects with its table models, over the
observations' times (the 0.0.2 client reads them only one by one). Ids are kept as strings
(a socat UUID, or the integer of 0.0.2 or of a file's ``source_id``; '' without one).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.table import Table

from so_transients.common.redact import redacted
from so_transients.common.step_config import ConfigError

log = logging.getLogger(__name__)

#: URL schemes read as a socat database.
DATABASE_SCHEMES = ("socat:", "sqlite:", "sqlite+", "postgresql:", "postgresql+")


@dataclass
class Catalogue:
    """Fixed sources: ``ra``, ``dec`` (radians), ``name``, ``source_id`` (str: socat's UUID or
    integer id, '' when the file has none), ``flux_mjy`` (NaN when unknown); ``label`` names
    the catalogue in tables."""

    label: str
    ra: np.ndarray
    dec: np.ndarray
    name: np.ndarray
    source_id: np.ndarray
    flux_mjy: np.ndarray

    def __len__(self):
        return len(self.ra)


@dataclass
class Ephemerides:
    """Ephemeris points of solar-system objects, one row per object and time: ``sso_id``
    (str), ``name``, ``time`` (ctime, s), ``ra``, ``dec`` (radians), ``flux_mjy`` (NaN when unknown)."""

    sso_id: np.ndarray
    name: np.ndarray
    time: np.ndarray
    ra: np.ndarray
    dec: np.ndarray
    flux_mjy: np.ndarray

    def __len__(self):
        return len(self.time)


def empty_ephemerides() -> Ephemerides:
    """No solar-system object (a catalogue file has none)."""
    return Ephemerides(np.zeros(0, str), np.zeros(0, str), *np.zeros((4, 0)))


def is_database_url(spec) -> bool:
    """True when ``spec`` names a socat database rather than a file."""
    return str(spec).startswith(DATABASE_SCHEMES)


def database_url(spec) -> str:
    """The SQLAlchemy URL of the socat database ``spec`` names (see the module)."""
    spec = str(spec)
    if spec == "socat:":
        from socat.settings import Settings

        return Settings().sync_database_url
    if spec.startswith("socat://"):                 # socat:///abs/path or socat://rel/path
        return "sqlite:///" + spec[len("socat://"):]
    if spec.startswith("socat:"):
        raise ValueError(f"catalogue {redacted(spec)!r}: expected `socat:` (socat's own settings) or "
                         "`socat:///path/socat.db`")
    return spec


def _require_socat(spec):
    try:
        import socat  # noqa: F401
    except ImportError:
        raise ImportError(f"catalogue {redacted(spec)!r} is a socat database: install the optional "
                          "`socat` package (pip install so_transients[catalog])") from None


def _session_factory(spec):
    """socat's sync session factory on the database ``spec``; a SQLite file must exist
    (socat would otherwise create an empty catalogue in its place)."""
    _require_socat(spec)
    from socat.database.session import create_sync_session_factory
    from sqlalchemy.engine import make_url

    url = database_url(spec)
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite":
        if not parsed.database or not Path(parsed.database).is_file():
            raise FileNotFoundError(f"catalogue {redacted(spec)!r}: no socat SQLite file at "
                                    f"{parsed.database!r}")
    return create_sync_session_factory(db_url=url)


def _flux_mjy(quantity) -> float:
    return np.nan if quantity is None else float(quantity.to_value(u.mJy))


def read_socat(spec) -> Catalogue:
    """The fixed sources of the socat database ``spec`` (see the module), with socat's DB
    client."""
    from astropy.coordinates import ICRS
    from socat.client.db import Client

    client = Client(session_factory=_session_factory(spec))
    # the whole sky (an RA of 360 deg would wrap to 0: the box ends just below it; socat
    # stores positions as ICRS, whose RA is below 360 deg); socat 0.1's get_box also wants
    # times (for its moving objects): its fixed sources are get_box_fixed
    box = getattr(client, "get_box_fixed", None) or client.get_box
    sources = box(lower_left=ICRS(ra=0 * u.deg, dec=-90 * u.deg),
                  upper_right=ICRS(ra=np.nextafter(360.0, 0) * u.deg, dec=90 * u.deg))
    if not sources:
        log.warning("catalogue %s holds no fixed source", redacted(spec))
    return Catalogue(
        label=redacted(spec),
        ra=np.array([s.position.ra.to_value(u.rad) for s in sources], float),
        dec=np.array([s.position.dec.to_value(u.rad) for s in sources], float),
        name=np.array([s.name or "" for s in sources], str),
        source_id=np.array([str(s.source_id) for s in sources], str),
        flux_mjy=np.array([_flux_mjy(s.flux) for s in sources], float))


def _time_is_datetime(table) -> bool:
    """Whether socat's ephemeris table keeps times as datetimes (0.1) or ctimes (0.0.2)."""
    import sqlalchemy as sa

    return isinstance(table.__table__.c.time.type, sa.DateTime)


def _ctime(when: datetime) -> float:
    """A socat datetime (UTC; naive as SQLite returns it) as ctime."""
    return (when if when.tzinfo else when.replace(tzinfo=timezone.utc)).timestamp()


def read_socat_ephemerides(spec, t_min, t_max, pad=86400.0) -> Ephemerides:
    """The ephemeris points of every solar-system object of the socat database ``spec``
    between ctimes ``t_min - pad`` and ``t_max + pad`` (the padding brackets the times
    asked for, as sotrplib pads its socat queries by a day)."""
    from socat.database import RegisteredMovingSourceTable, SolarSystemObjectTable
    from sqlmodel import select

    lo, hi = int(np.floor(t_min - pad)), int(np.ceil(t_max + pad))
    as_datetime = _time_is_datetime(RegisteredMovingSourceTable)
    if as_datetime:          # socat 0.1 stores UTC datetimes, 0.0.2 ctimes
        lo, hi = (datetime.fromtimestamp(t, timezone.utc) for t in (lo, hi))
    with _session_factory(spec)() as session:
        rows = session.execute(
            select(RegisteredMovingSourceTable, SolarSystemObjectTable.name)
            .join(SolarSystemObjectTable,
                  SolarSystemObjectTable.sso_id == RegisteredMovingSourceTable.sso_id)
            .where(RegisteredMovingSourceTable.time >= lo, RegisteredMovingSourceTable.time <= hi)
            .order_by(RegisteredMovingSourceTable.sso_id, RegisteredMovingSourceTable.time)
        ).all()
    return Ephemerides(
        sso_id=np.array([str(r[0].sso_id) for r in rows], str),
        name=np.array([r[1] for r in rows], str),
        time=np.array([_ctime(r[0].time) if as_datetime else r[0].time for r in rows], float),
        ra=np.radians(np.array([r[0].ra_deg for r in rows], float)),
        dec=np.radians(np.array([r[0].dec_deg for r in rows], float)),
        flux_mjy=np.array([np.nan if r[0].flux_mJy is None else r[0].flux_mJy for r in rows],
                          float))


def _column(table, name, default_unit, target, path):
    """Column ``name`` in ``target`` units (``default_unit`` when the column carries none)."""
    col = table[name]
    quantity = (col.quantity if col.unit is not None
                else np.asarray(col, float) * u.Unit(default_unit))
    try:
        return np.asarray(quantity.to_value(target), float)
    except u.UnitConversionError:
        raise ValueError(f"catalogue {path}: column {name!r} is in {col.unit}, which does not "
                         f"convert to {target}") from None


#: Accepted coordinate ranges (degrees) of a known-source list: RA in [0, 360) or (-180, 180],
#: Dec in [-90, 90]. A value outside them is a wrong unit or a corrupt row.
KNOWN_SOURCE_RANGE_DEG = {"ra": (-180.0, 360.0), "dec": (-90.0, 90.0)}


def read_source_table(path, unit="deg", owner="catalogue", unit_key="unit"):
    """``(table, ra, dec)`` of an ECSV or CSV file with ``ra`` and ``dec`` columns (radians).

    ``unit``: the unit of columns that carry none (``unit_key``: the config key giving it).
    A file that is missing, empty (0 bytes) or unreadable, lacks a column, or holds a
    non-numeric, missing or out-of-range value (:data:`KNOWN_SOURCE_RANGE_DEG`) raises a
    :class:`~so_transients.common.step_config.ConfigError` naming ``owner`` (for a step's key:
    ``"transient_cuts: known_sources"``) and the file; a list with no rows (a header only) is
    allowed with a warning that nothing will be masked or matched.
    """
    where = f"{owner}: {path}"
    file = Path(path)
    if not file.exists():
        raise ConfigError(f"{where}: no such file (resolved: {file.resolve()})")
    if not file.is_file():
        raise ConfigError(f"{where}: not a file (resolved: {file.resolve()})")
    if file.stat().st_size == 0:
        raise ConfigError(f"{where}: the file is empty (0 bytes); a list without sources "
                          "needs its header (ra, dec), or set the key to null")
    fmt = "ascii.ecsv" if file.suffix == ".ecsv" else "ascii.csv"
    try:
        table = Table.read(file, format=fmt)
    except Exception as exc:     # astropy raises many types; each becomes one line naming the file
        reason = (str(exc).strip().splitlines() or [""])[0]
        raise ConfigError(f"{where}: cannot be read as {fmt or 'a table'} "
                          f"({type(exc).__name__}: {reason})") from exc
    missing = [name for name in ("ra", "dec") if name not in table.colnames]
    if missing:
        raise ConfigError(f"{where}: lacks column(s) {', '.join(missing)} (has: "
                          f"{', '.join(table.colnames) or 'none'})")
    try:
        default_unit = u.Unit(unit)
        default_unit.to(u.deg)
    except (ValueError, TypeError, u.UnitsError):
        raise ConfigError(f"{unit_key}: {unit!r} is not an angle unit") from None
    if len(table) == 0:
        log.warning("%s: lists no sources: nothing will be masked or matched", where)
    ra, dec = (_angle_column(table[name], name, default_unit, where, unit_key)
               for name in ("ra", "dec"))
    return table, ra, dec


def read_known_sources(path, unit="deg", step="transient_cuts", key="known_sources"):
    """RA, Dec (radians) of a known-source file, checked as :func:`read_source_table` says,
    errors naming ``step`` and ``key``."""
    _, ra, dec = read_source_table(path, unit, f"{step}: {key}", f"{step}: {key}_unit")
    return ra, dec


def _angle_column(col, name, default_unit, where, unit_key):
    """Column ``name`` of a source table in radians, checked as :func:`read_source_table`
    describes (``unit_key``: the key giving ``default_unit``)."""
    if col.dtype.kind not in "iuf":
        first = f", first value {col[0]!r}" if len(col) else ""
        raise ConfigError(f"{where}: column {name} is not numeric (type {col.dtype}{first})")
    values = np.ma.filled(np.ma.asarray(col, dtype=float), np.nan)
    bad = np.flatnonzero(~np.isfinite(values))
    if len(bad):
        raise ConfigError(f"{where}: column {name} has {len(bad)} missing or non-finite "
                          f"value(s), the first in data row {bad[0] + 1}")
    unit = col.unit if col.unit is not None else default_unit
    try:
        degrees = (values * u.Unit(unit)).to_value(u.deg)
    except (ValueError, TypeError, u.UnitsError):
        raise ConfigError(f"{where}: column {name} has unit {unit}, not an angle") from None
    lo, hi = KNOWN_SOURCE_RANGE_DEG[name]
    out = np.flatnonzero((degrees < lo) | (degrees > hi))
    if len(out):
        raise ConfigError(f"{where}: column {name} must lie in [{lo:g}, {hi:g}] deg; data "
                          f"row {out[0] + 1} has {values[out[0]]:g} {unit} (a wrong unit? a "
                          f"column without one is read in {unit_key})")
    return np.radians(degrees)


def read_table_catalogue(path, unit="deg", owner="catalogue", unit_key="unit") -> Catalogue:
    """The sources of an ECSV or CSV file (see the module), checked by
    :func:`read_source_table` (``owner``, ``unit_key``: what its errors name); ``unit``: of
    ``ra``/``dec`` when the columns carry none."""
    table, ra, dec = read_source_table(path, unit, owner, unit_key)
    n = len(table)
    return Catalogue(
        label=str(path), ra=ra, dec=dec,
        name=np.asarray(table["name"], str) if "name" in table.colnames else np.full(n, ""),
        source_id=(np.asarray(table["source_id"]).astype(str) if "source_id" in table.colnames
                   else np.full(n, "")),
        flux_mjy=(_column(table, "flux", "mJy", u.mJy, path) if "flux" in table.colnames
                  else np.full(n, np.nan)))


def read_catalogue(spec, unit="deg", owner="catalogue", unit_key="unit") -> Catalogue:
    """The fixed sources ``spec`` names: a socat database URL or an ECSV/CSV file (errors
    name ``owner``: the step and key, or the events config's key)."""
    if is_database_url(spec):
        return read_socat(spec)
    return read_table_catalogue(spec, unit, owner, unit_key)


def read_ephemerides(spec, t_min, t_max) -> Ephemerides:
    """Ephemeris points around ``[t_min, t_max]`` from a socat database; none from a file."""
    if not is_database_url(spec):
        return empty_ephemerides()
    return read_socat_ephemerides(spec, t_min, t_max)
