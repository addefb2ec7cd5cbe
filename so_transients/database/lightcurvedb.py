"""Light-curve points to and from lightcurvedb's ``FluxMeasurement`` (simonsobs/lightcurvedb,
``lightcurvedb/models/flux.py``): ``measurement_id`` (UUID), ``frequency`` (int, GHz),
``module`` (the optics tube, e.g. ``i1``), ``source_id`` (UUID), ``time`` (datetime, UTC),
``ra``, ``dec`` (degrees, RA in [-180, 180) as lightcurvedb stores it), ``ra_uncertainty``,
``dec_uncertainty`` (degrees, None when unknown), ``flux``, ``flux_err`` (**Jy**, as sotrplib
writes them and lightserve and lightview show them; the package's tables are in mJy) and
``extra`` (``{"flags": [...]}``).

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

from so_transients.site.results import utc

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


def json_ready(measurement: dict) -> dict:
    """A FluxMeasurement dict with UUIDs and the time as strings (for JSON)."""
    out = dict(measurement)
    for key in ("measurement_id", "source_id"):
        out[key] = str(out[key])
    out["time"] = out["time"].isoformat()
    return out
