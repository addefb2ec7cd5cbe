"""Light-curve points to and from lightcurvedb's ``FluxMeasurement`` (simonsobs/lightcurvedb,
``lightcurvedb/models/flux.py``): ``measurement_id`` (UUID), ``frequency`` (int, GHz),
``module`` (the optics tube, e.g. ``i1``), ``source_id`` (UUID), ``time`` (datetime, UTC),
``ra``, ``dec`` (degrees, RA in [-180, 180) as lightcurvedb stores it), ``ra_uncertainty``,
``dec_uncertainty`` (degrees, None when unknown), ``flux``, ``flux_err`` (**Jy**, as sotrplib
writes them and lightserve and lightview show them; the package's tables are in mJy) and
``extra`` (``{"flags": [...]}``).

A source's records as lightcurvedb ingests them (:func:`source_records`): its ``Source``
(``source_id`` the persistent source's UUID, ``name``, ``ra`` in [-180, 180), ``dec``,
``socat_id`` and a cross-match when it matched an integer socat id), one ``Instrument`` per
band and tube it was measured in (``frequency``, ``module``, ``telescope`` LAT, ``instrument``
SO), its ``FluxMeasurement`` points, and its ``Cutout`` per event and band (the map in Jy, tied to
the measurement of its crossing).

``extra.flags`` are quality flags: lightview hides a flagged point. The points carry none (a
measurement that failed is not a light-curve point); what lightcurvedb has no field for (the
observation, wafer and scan, whether the event was detected at that crossing, the upper
limit) stays in the database's ``lightcurve_points``. ``measurement_id`` is a UUID derived
from the source, observation, wafer, band, scan and time: the same point ingested again gets
the same id.
"""
from __future__ import annotations

import uuid
from datetime import datetime, timezone

import numpy as np

from so_transients.common.times import utc

#: The fields of lightcurvedb's FluxMeasurement, in its order.
FIELDS = ("measurement_id", "frequency", "module", "source_id", "time", "ra", "dec",
          "ra_uncertainty", "dec_uncertainty", "flux", "flux_err", "extra")

#: Namespace of the measurement ids.
NAMESPACE = uuid.uuid5(uuid.NAMESPACE_URL, "so_transients/lightcurve_points")

#: mJy (the package's flux unit) per Jy (lightcurvedb's)
MJY_PER_JY = 1000.0


def _optional(value):
    value = float(value)
    return value if np.isfinite(value) else None


def measurement_id(source_uuid, point) -> uuid.UUID:
    """The id of light-curve ``point`` of source ``source_uuid``."""
    key = "/".join(str(point[k]) for k in ("obs_id", "wafer_slot", "bandpass", "scan"))
    return uuid.uuid5(NAMESPACE, f"{source_uuid}/{key}/{float(point['ctime']):.6f}")


def to_flux_measurement(point, source_uuid) -> dict:
    """The FluxMeasurement fields (a dict, ready for ``FluxMeasurement(**...)``) of one
    light-curve point (a mapping with the ``lightcurves`` table's columns) of the source whose
    UUID is ``source_uuid``."""
    ra = float(point["ra"])
    return dict(
        measurement_id=measurement_id(source_uuid, point),
        frequency=int(point["frequency"]),
        module=str(point["module"]),
        source_id=uuid.UUID(str(source_uuid)),
        time=datetime.fromtimestamp(float(point["ctime"]), tz=timezone.utc),
        ra=(ra + 180.0) % 360.0 - 180.0,
        dec=float(point["dec"]),
        ra_uncertainty=_optional(point["ra_uncertainty"]),
        dec_uncertainty=_optional(point["dec_uncertainty"]),
        flux=float(point["flux"]) / MJY_PER_JY,
        flux_err=float(point["flux_err"]) / MJY_PER_JY,
        extra={"flags": []},
    )


def from_flux_measurement(measurement) -> dict:
    """The light-curve point of a FluxMeasurement (a mapping of its fields, or the model
    itself): the ``lightcurves`` columns lightcurvedb carries (``time`` as ISO UTC, ``ctime``,
    ``ra`` in [0, 360), ``dec``, uncertainties (NaN when unknown), ``flux``, ``flux_err`` (mJy),
    ``frequency``, ``module``, ``bandpass``, ``snr``), with ``source_uuid`` and
    ``measurement_id``."""
    m = measurement if isinstance(measurement, dict) else dict(measurement)
    time = m["time"]
    if isinstance(time, str):
        time = datetime.fromisoformat(time)
    if time.tzinfo is None:
        time = time.replace(tzinfo=timezone.utc)
    nan = lambda v: np.nan if v is None else float(v)
    point = dict(
        source_uuid=str(m["source_id"]), measurement_id=str(m["measurement_id"]),
        time=str(utc(time.timestamp())[0]), ctime=time.timestamp(),
        ra=float(m["ra"]) % 360.0, dec=float(m["dec"]),
        ra_uncertainty=nan(m["ra_uncertainty"]), dec_uncertainty=nan(m["dec_uncertainty"]),
        flux=float(m["flux"]) * MJY_PER_JY, flux_err=float(m["flux_err"]) * MJY_PER_JY,
        frequency=int(m["frequency"]), module=str(m["module"]),
        bandpass=f"f{int(m['frequency']):03d}",
    )
    point["snr"] = point["flux"] / point["flux_err"] if point["flux_err"] else np.nan
    return point


def json_ready(record: dict) -> dict:
    """A record dict with UUIDs and times as strings (for JSON)."""
    out = dict(record)
    for key, value in out.items():
        if isinstance(value, uuid.UUID):
            out[key] = str(value)
        elif isinstance(value, datetime):
            out[key] = value.isoformat()
    return out


#: Fields of lightcurvedb's Source, Instrument and Cutout (lightcurvedb/models).
SOURCE_FIELDS = ("source_id", "socat_id", "name", "ra", "dec", "variable", "extra")
INSTRUMENT_FIELDS = ("frequency", "module", "telescope", "instrument", "details")
CUTOUT_FIELDS = ("measurement_id", "data", "time", "units", "frequency", "module", "source_id")


def _socat_id(value):
    """lightcurvedb's integer ``socat_id`` of a catalogue id (socat 0.1's UUIDs: None)."""
    try:
        return int(value)
    except (TypeError, ValueError):
        return None


def to_source(source: dict, events) -> dict:
    """lightcurvedb's Source of a stored source (its row) and its ``events`` (rows with the
    cross-match columns)."""
    matched = [e for e in events if str(e["catalogue"])]
    socat = _socat_id(matched[0]["cat_source_id"]) if matched else None
    names = sorted({str(e["cat_source_name"]) for e in matched if str(e["cat_source_name"])})
    return dict(source_id=uuid.UUID(str(source["uuid"])), socat_id=socat,
                name=str(source["name"]), ra=(float(source["ra"]) + 180.0) % 360.0 - 180.0,
                dec=float(source["dec"]), variable=True,     # it flared
                extra={"cross_matches": [{"name": n} for n in names], "socat_id": socat})


def to_instruments(points) -> list:
    """One lightcurvedb Instrument per band (``frequency``) and tube (``module``) of
    ``points``."""
    pairs = sorted({(int(p["frequency"]), str(p["module"])) for p in points})
    return [dict(frequency=f, module=m, telescope="LAT", instrument="SO",
                 details={"bandpass": f"f{f:03d}"}) for f, m in pairs]


def to_cutout(cutout, point, source_uuid) -> dict:
    """lightcurvedb's Cutout of a stored cutout row (``data`` in Jy, None where nothing fell:
    0 there, as its model takes floats) measured at light-curve ``point``."""
    data = [[0.0 if v is None else float(v) for v in row] for row in cutout["data"]]
    return dict(measurement_id=measurement_id(source_uuid, point), data=data,
                time=datetime.fromtimestamp(float(cutout["ctime"]), tz=timezone.utc),
                units="Jy", frequency=int(cutout["frequency"]), module=str(point["module"]),
                source_id=uuid.UUID(str(source_uuid)))
