"""Alert records from an events table, in the GCN unified schema's core fields.

The record's JSON Schema is ``alert.schema.json`` beside this module (:func:`load_schema`);
every record made here is validated against it before it is returned. Field names and units
follow nasa-gcn/gcn-schema v7.2.1 (``gcn/notices/core``): ``alert_tense``, ``alert_type``,
``trigger_time`` (ISO UTC), ``ra``, ``dec``, ``ra_dec_error`` (deg), ``far`` (Hz, for the
whole instrument, as GCN means it: the events' rate per wafer-band times the
``wafer_bands`` searched at once; the per-wafer-band rate beside it), ``flux_density`` in
erg/cm2/s/Hz (1 mJy = 1e-26 erg/cm2/s/Hz) with the value in mJy beside it.

An alert's history is the folder it is written to: each alert is one JSON file
``<id>-<record_number>.json``; a new run over a later events table reads the folder and, for
each event,

* that qualifies (S/N at least ``min_snr``, ``far`` at most ``max_far_hz`` when set, and not a
  catalogued source at its flux or a solar-system object) and matches no earlier alert (within
  ``match_radius_arcmin`` and ``max_gap_s`` of its detections): an ``initial`` alert;
* that matches an earlier alert and changed: ``subsequent`` when seen in a new observation,
  ``update`` when a re-analysis of the same observations changed it;
* an earlier alert whose event no longer qualifies (now catalogued or a solar-system object,
  now below ``min_snr``), or is gone from a re-analysis of all its observations: a
  ``retraction`` naming the reason. An event absent from a run that did not cover its
  observations is left alone.
"""
from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from datetime import datetime, timezone
from functools import lru_cache
from importlib import resources
from pathlib import Path

import jsonschema    # the `alerts` extra
import numpy as np
from astropy.table import Table
from astropy.time import Time

from so_transients.common.angles import ARCMIN, DEG, sky_separation
from so_transients.common.bands import CENTER_GHZ, FLAVOR_BANDS, HARDWARE_BAND_KEY, nominal_hardware
from so_transients.common.step_config import positive, setting

log = logging.getLogger(__name__)

SCHEMA_FILE = "alert.schema.json"
#: 1 mJy in erg/cm2/s/Hz (1 Jy = 1e-23 erg/cm2/s/Hz)
MJY_CGS = 1e-26
#: radius of the 90 % circle of a circular 2-D Gaussian, in units of its one-axis sigma
CONTAINMENT_90 = float(np.sqrt(-2 * np.log(0.1)))
#: cross-match classes that are transients: alerted
ALERTED_CLASSES = ("new", "catalogued_flare", "")
#: fields that do not describe the event (compared to tell whether it changed)
#: The column of cutout files (comma-separated) the alerts command gives each event.
CUTOUT_FILES = "cutout_files"

BOOKKEEPING = ("$schema", "alert_datetime", "alert_type", "record_number", "update_message",
               "supersedes")


@dataclass
class AlertsConfig:
    min_snr: float = setting(6.0, "", "alert events with at least this S/N (joint two-band S/N, "
                             "else the brightest detection's)")
    max_far_hz: float | None = setting(
        None, "Hz", "and, when set, an instrument-level false-alarm rate at most this")
    match_radius_arcmin: float = setting(
        0.5, "arcmin", "an event within this of an earlier alert's position ...")
    max_gap_s: float = setting(
        600.0, "s", "... and its detections within this of the earlier ones continues that alert")
    injection_radius_arcmin: float = setting(
        0.5, "arcmin", "simulations: an event this close to an injected flare ...")
    injection_pad_s: float = setting(
        5.0, "s", "... within its active window padded by this is an injection")
    wafer_bands: int = setting(
        36, "", "wafer-bands searched at once: an event's far per wafer-band times this is the "
        "instrument's (the LAT: 6 tubes x 3 wafers x 2 bands)")

    def __post_init__(self):
        positive("alerts", min_snr=self.min_snr, max_far_hz=self.max_far_hz,
                 match_radius_arcmin=self.match_radius_arcmin, max_gap_s=self.max_gap_s,
                 injection_radius_arcmin=self.injection_radius_arcmin,
                 injection_pad_s=self.injection_pad_s, wafer_bands=self.wafer_bands)


@lru_cache(maxsize=1)
def load_schema() -> dict:
    """The alert record's JSON Schema (package data)."""
    return json.loads(resources.files("so_transients.alerts").joinpath(SCHEMA_FILE).read_text())


def validate(record: dict):
    """Raise a ValueError naming the alert and every field that breaks the schema."""
    validator = jsonschema.Draft202012Validator(load_schema())
    errors = sorted(validator.iter_errors(record), key=lambda e: list(e.path))
    if errors:
        where = f"alert {record.get('id', '?')} #{record.get('record_number', '?')}"
        raise ValueError(f"{where} does not follow {SCHEMA_FILE}: " + "; ".join(
            f"{'/'.join(map(str, e.path)) or '(record)'}: {e.message}" for e in errors))


def iso_z(ctime) -> str:
    """ISO 8601 UTC with a Z, to the millisecond."""
    return Time(float(ctime), format="unix").isot + "Z"


def now_utc() -> str:
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def band_edges_mhz(band) -> list:
    """Low and high edge of a band (MHz), from sotodlib's nominal LAT hardware model."""
    props = nominal_hardware().data["bands"][HARDWARE_BAND_KEY[str(band)]]
    return [float(props["low"]) * 1e3, float(props["high"]) * 1e3]


def significance(events: Table) -> np.ndarray:
    """S/N of each event (a table, or one row): ``joint_snr`` where measured, else the brightest detection's
    ``peak_flux / peak_flux_err``."""
    joint = np.asarray(events["joint_snr"], float)
    peak = np.asarray(events["peak_flux"], float) / np.asarray(events["peak_flux_err"], float)
    return np.where(np.isfinite(joint), joint, peak)


def far_hz(events: Table, wafer_bands=1) -> np.ndarray:
    """The events' false-alarm rate in Hz: their ``far`` (per wafer-band-hour) times
    ``wafer_bands`` (the instrument's rate with the number it searches); NaN where not
    measured."""
    if "far" not in events.colnames:
        return np.full(np.shape(events["ra"]), np.nan)
    return np.asarray(events["far"], float) / 3600.0 * wafer_bands


def alert_id(event) -> str:
    """``SO-LAT-<ctime of the first detection>-<8 hex>``: fixed by the initial alert."""
    digest = hashlib.sha1(f"{event['name']}|{float(event['t_first']):.3f}".encode()).hexdigest()
    return f"SO-LAT-{int(event['t_first'])}-{digest[:8]}"


def _split(value) -> list:
    return [v for v in str(value).split(",") if v]


def _finite(value) -> bool:
    return value is not None and bool(np.isfinite(value))


def _spectral_index(event) -> dict:
    for (band_a, band_b), name in zip(FLAVOR_BANDS.values(), ("alpha_mf", "alpha_uhf")):
        if _finite(event[name]) and _finite(event[f"{name}_err"]):
            return dict(spectral_index=float(event[name]),
                        spectral_index_error=float(event[f"{name}_err"]),
                        spectral_index_bands=f"{band_a}/{band_b}")
    return {}


def _duration(event, fits: Table | None) -> dict:
    if fits is None or not len(fits):
        return {}
    mine = fits[(fits["event_id"] == event["event_id"]) & (fits["bandpass"] == event["peak_band"])]
    if not len(mine) or not mine["fit_ok"][0]:
        return {}
    fit = mine[0]
    duration = float(fit["t_rise"] + fit["t_decay"])
    error = float(np.hypot(np.nan_to_num(fit["t_rise_err"]), np.nan_to_num(fit["t_decay_err"])))
    return dict(duration=duration, duration_error=error) if np.isfinite(duration) else {}


def _crossmatch(event) -> dict:
    cls = str(event["cat_class"]) if "cat_class" in event.colnames else ""
    out = dict(crossmatch_class=cls)
    if cls == "catalogued_flare":
        out.update(catalogue=str(event["catalogue"]), known_source=str(event["cat_source_name"]),
                   known_source_id=str(event["cat_source_id"]),
                   known_source_separation=float(event["cat_separation"]))
        if _finite(event["cat_flux_ratio"]):
            out["flux_ratio"] = float(event["cat_flux_ratio"])
    return out


def _cutouts(event) -> dict:
    """The event's sky cutouts (``cutout_files``, a column the alerts command adds from the
    events folder's cutouts.ecsv): their files, relative to the events folder."""
    if CUTOUT_FILES not in event.colnames or not str(event[CUTOUT_FILES]):
        return {}
    return {"cutouts": str(event[CUTOUT_FILES]).split(",")}


def event_record(event, fits, tense, ident, record_number, alert_type, created,
                 supersedes=None, message=None, wafer_bands=AlertsConfig.wafer_bands) -> dict:
    """One alert of an event (a row of the events table; ``fits``: the lightcurve_fits table
    or None; ``wafer_bands``: the instrument's, for its ``far``)."""
    band = str(event["peak_band"])
    flux, flux_err = float(event["peak_flux"]), float(event["peak_flux_err"])
    record = {
        "$schema": load_schema()["$id"], "alert_datetime": created, "alert_tense": tense,
        "alert_type": alert_type, "mission": "Simons Observatory", "instrument": "LAT",
        "record_number": int(record_number), "messenger": "EM",
        "spectral_band": band_edges_mhz(band), "spectral_band_units": "MHz",
        "id": ident, "event_name": str(event["name"]),
        "trigger_time": iso_z(event["t_first"]), "last_detection_time": iso_z(event["t_last"]),
        "ra": float(event["ra"]), "dec": float(event["dec"]),
        "ra_dec_error": CONTAINMENT_90 * float(event["pos_err"]) / 3600.0,
        "containment_probability": 0.9, "systematic_included": False,
        "snr": float(significance(event)),
        "detection_span": float(event["t_last"] - event["t_first"]),
        "flux_density": flux * MJY_CGS, "flux_density_error": flux_err * MJY_CGS,
        "flux_density_unit": "erg/cm2/s/Hz",
        "flux_density_spectral_point": CENTER_GHZ[band] * 1e3,
        "flux_density_spectral_point_unit": "MHz",
        "flux_density_mjy": flux, "flux_density_error_mjy": flux_err, "peak_band": band,
        "bands": _split(event["bands"]), "wafers": _split(event["wafers"]),
        "obs_ids": _split(event["obs_ids"]), "so_event_id": str(event["event_uuid"]),
        "so_source_id": str(event["source_uuid"]),
        **_spectral_index(event), **_duration(event, fits), **_crossmatch(event),
        **_cutouts(event),
    }
    far = float(far_hz(event, wafer_bands))
    if np.isfinite(far):
        record["far"] = float(far)
        record["far_per_wafer_band"] = float(far_hz(event))
        record["far_wafer_bands"] = int(wafer_bands)
        record["far_is_upper_limit"] = bool(event["far_is_limit"]) \
            if "far_is_limit" in event.colnames else False
    if supersedes:
        record.update(supersedes=supersedes, update_message=message)
    validate(record)
    return record


def retraction_record(previous: dict, reason, created) -> dict:
    """The retraction of the alert ``previous`` (its latest record)."""
    record = {"$schema": load_schema()["$id"], "alert_datetime": created,
              "alert_tense": previous["alert_tense"], "alert_type": "retraction",
              "mission": "Simons Observatory", "instrument": "LAT",
              "record_number": previous["record_number"] + 1, "id": previous["id"],
              "trigger_time": previous["trigger_time"], "update_message": reason,
              "supersedes": file_name(previous)}
    validate(record)
    return record


def file_name(record) -> str:
    return f"{record['id']}-{record['record_number']:02d}.json"


def read_alerts(folder) -> dict:
    """``{id: [records in record_number order]}`` of the alert files in ``folder``."""
    history = {}
    for path in sorted(Path(folder).glob("SO-LAT-*.json")):
        try:
            record = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not an alert (invalid JSON: {exc})") from None
        if record.get("id") is None or file_name(record) != path.name:
            raise ValueError(f"{path}: not an alert of this folder (its id and record_number "
                             "do not give its file name)")
        history.setdefault(record["id"], []).append(record)
    return {k: sorted(v, key=lambda r: r["record_number"]) for k, v in history.items()}


def _ctime(iso) -> float:
    return float(Time(iso.rstrip("Z"), format="isot", scale="utc").unix)


def match_previous(events: Table, history: dict, cfg: AlertsConfig) -> dict:
    """``{alert id: event row index}``: each earlier alert continued by an event within
    ``match_radius_arcmin`` of its position: the same source. An event whose detections are
    within ``max_gap_s`` of the alert's is preferred (the same flare), then the nearest; an
    event continues at most one alert."""
    pairs = []
    for ident, records in history.items():
        placed = [r for r in records if "ra" in r]
        if not placed or not len(events):
            continue
        last = placed[-1]
        sep = sky_separation(np.radians(np.asarray(events["ra"], float)),
                             np.radians(np.asarray(events["dec"], float)),
                             last["ra"] * DEG, last["dec"] * DEG)
        near_time = same_flare(events, last, cfg)
        for i in np.flatnonzero(sep <= cfg.match_radius_arcmin * ARCMIN):
            pairs.append((not near_time[i], sep[i], ident, int(i)))
    matched, used = {}, set()
    for _, _, ident, i in sorted(pairs):
        if ident not in matched and i not in used:
            matched[ident] = i
            used.add(i)
    return matched


def same_flare(events, record, cfg: AlertsConfig) -> np.ndarray:
    """Whether each event's detections are within ``max_gap_s`` of those of an alert
    ``record``: the same flare, where a later one of the same source is not."""
    t0, t1 = _ctime(record["trigger_time"]), _ctime(record["last_detection_time"])
    return ((np.atleast_1d(events["t_last"]) >= t0 - cfg.max_gap_s)
            & (np.atleast_1d(events["t_first"]) <= t1 + cfg.max_gap_s))


def qualifies(events: Table, cfg: AlertsConfig) -> np.ndarray:
    """Events that are alerted: S/N, false-alarm rate and cross-match class."""
    ok = significance(events) >= cfg.min_snr
    if cfg.max_far_hz is not None:
        far = far_hz(events, cfg.wafer_bands)
        ok &= np.isfinite(far) & (far <= cfg.max_far_hz)
    if "cat_class" in events.colnames:
        ok &= np.isin(np.asarray(events["cat_class"], str), ALERTED_CLASSES)
    return ok


def _why_not(event, cfg: AlertsConfig) -> str:
    """Why an event that was alerted no longer qualifies."""
    cls = str(event["cat_class"]) if "cat_class" in event.colnames else ""
    if cls == "catalogued":
        return (f"a catalogued source at its catalogue flux: {event['cat_source_name']} "
                f"({event['catalogue']}), {event['cat_separation']:.2f} arcmin away, flux ratio "
                f"{event['cat_flux_ratio']:.2f}")
    if cls == "solar_system":
        return (f"a solar-system object: {event['cat_source_name']} ({event['catalogue']} "
                f"ephemeris), {event['cat_separation']:.2f} arcmin away")
    snr = float(significance(event))
    if snr < cfg.min_snr:
        return f"its S/N is now {snr:.1f}, below {cfg.min_snr:g}"
    far = float(far_hz(event, cfg.wafer_bands))
    return f"its false-alarm rate is now {far:.3g} Hz, above {cfg.max_far_hz:g}"


def changes(old: dict, new: dict) -> list:
    """Fields (other than bookkeeping) whose value differs between two records."""
    keys = (set(old) | set(new)) - set(BOOKKEEPING)
    return sorted(k for k in keys if old.get(k) != new.get(k))


def plan_alerts(events: Table, fits: Table | None, tenses, history: dict, covered_obs,
                cfg: AlertsConfig, created=None) -> list:
    """The new alert records for ``events`` given the earlier alerts ``history``
    (:func:`read_alerts`); ``tenses``: each event's alert tense; ``covered_obs``: the
    observations the events table was made from (a retraction for an event gone from the
    table needs all of its observations re-analysed)."""
    created = created or now_utc()
    ok = qualifies(events, cfg)
    matched = match_previous(events, history, cfg)
    continued = set(matched.values())
    out = []
    for i in np.flatnonzero(ok):
        if int(i) in continued:
            continue
        record = event_record(events[i], fits, tenses[i], alert_id(events[i]), 1, "initial",
                              created, wafer_bands=cfg.wafer_bands)
        if record["id"] in history:
            raise ValueError(f"event {events['event_id'][i]} ({events['name'][i]}) has the id "
                             f"{record['id']} of an earlier alert it does not continue")
        out.append(record)
    covered = {str(o) for o in covered_obs}
    for ident, records in sorted(history.items()):
        last = records[-1]
        if ident in matched:
            i = matched[ident]
            if ok[i]:
                out.extend(_continuation(events[i], fits, tenses[i], records, created, cfg))
            elif last["alert_type"] != "retraction":
                out.append(retraction_record(last, _why_not(events[i], cfg), created))
        elif last["alert_type"] != "retraction":
            placed = [r for r in records if "obs_ids" in r][-1]
            if set(placed["obs_ids"]) <= covered:
                out.append(retraction_record(
                    last, "no event at its position in a re-analysis of its observations "
                    f"({', '.join(placed['obs_ids'])})", created))
    return out


def _continuation(event, fits, tense, records, created, cfg: AlertsConfig) -> list:
    """The subsequent or update alert of an event that continues ``records`` (none when
    nothing changed). Its ``so_source_id`` is the first alert's: one source id per position
    across observations, whichever run's events table it comes from."""
    last = records[-1]
    placed = [r for r in records if "ra" in r]
    source = placed[0]["so_source_id"]
    placed = placed[-1]

    def record(kind, **extra):
        new = event_record(event, fits, tense, last["id"], last["record_number"] + 1, kind,
                           created, wafer_bands=cfg.wafer_bands, **extra)
        new["so_source_id"] = source
        return new

    new = record("initial")
    changed = changes(placed, new)
    if last["alert_type"] != "retraction" and not changed:
        return []
    seen_again = sorted(set(new["obs_ids"]) - set(placed["obs_ids"]))
    if last["alert_type"] == "retraction":
        kind, message = "update", "alerted again after its retraction: it qualifies in a " \
                                  "later analysis"
    elif not bool(same_flare(event, placed, cfg)[0]):
        gap = float(event["t_first"]) - _ctime(placed["last_detection_time"])
        kind, message = "subsequent", (f"a new flare of the same source, {gap / 3600:.1f} h "
                                       f"after its last alerted detection"
                                       + (f", in {', '.join(seen_again)}" if seen_again else ""))
    elif seen_again:
        kind, message = "subsequent", f"seen again in {', '.join(seen_again)}"
    else:
        kind, message = "update", f"re-analysis changed {', '.join(changed)}"
    return [record(kind, supersedes=file_name(last), message=message)]
