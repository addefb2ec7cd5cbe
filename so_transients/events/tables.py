"""Building the event tables from detections and forced photometry.

:func:`associate_detections` joins a run's detections into events (and events into
sources); :func:`lightcurve_table` turns the work units' forced photometry into the
``lightcurves`` table; :func:`fit_table` fits eq. 1 per event and band; :func:`complete_events`
adds what the light curves tell about each event (multi-band significance, spectral indices,
counts, and a note of anything that could not be measured); :func:`crossmatch_events` the
nearest catalogued source. Columns: :mod:`.schema`.
"""
from __future__ import annotations

import uuid

import numpy as np
from astropy.table import Table

from so_transients.common.angles import ARCSEC
from so_transients.events.association import (
    AssociationConfig, link, position_sigma, weighted_position
)
from so_transients.common.bands import FLAVOR_BANDS
from so_transients.common.candidates import typed_table
from so_transients.events.lightcurve_fit import (
    FLARE_PARAMS, FlareFitConfig, fit_flare, spectral_index
)
from so_transients.common.times import utc
from so_transients.sources.catalog import Catalogue, Ephemerides
from so_transients.sources.crossmatch import CrossmatchConfig, crossmatch
from so_transients.events import schema


def event_name(ra_deg, dec_deg) -> str:
    """``SOTR Jhhmmss.s+ddmmss.s`` of a position in degrees, truncated as the IAU's naming
    convention asks (rounding would name RA 359.9998 deg ``J240000.0``)."""
    tenths = int(np.floor((float(ra_deg) % 360.0) / 15.0 * 36000.0 + 1e-6)) % (24 * 36000)
    h, rest = divmod(tenths, 36000)
    m, s10 = divmod(rest, 600)
    sign = "-" if dec_deg < 0 else "+"
    arc = int(np.floor(abs(float(dec_deg)) * 36000.0 + 1e-6))
    d, rest = divmod(arc, 36000)
    am, as10 = divmod(rest, 600)
    return (f"SOTR J{h:02d}{m:02d}{s10 // 10:02d}.{s10 % 10}"
            f"{sign}{d:02d}{am:02d}{as10 // 10:02d}.{as10 % 10}")


#: Namespace of the events' and sources' UUIDs (:func:`event_uuid`, :func:`source_uuid`).
UUID_NAMESPACE = uuid.UUID("5b0c6a4e-2f0d-5d8e-9a51-53494d4f4e53")


def event_uuid(obs_id, wafer_slot, bandpass, scan, t_peak) -> str:
    """The UUID of an event whose first detection is this one: a name-based UUID (version 5)
    of its observation, wafer, band, scan and peak time to 0.1 s, so that every run and every
    re-ingest that finds that detection first gives the event the same id."""
    key = f"event:{obs_id}:{wafer_slot}:{bandpass}:{int(scan)}:{float(t_peak):.1f}"
    return str(uuid.uuid5(UUID_NAMESPACE, key))


def source_uuid(first_event_uuid) -> str:
    """The UUID of a source whose first event is ``first_event_uuid``."""
    return str(uuid.uuid5(UUID_NAMESPACE, f"source:{first_event_uuid}"))


def _first_detection_uuid(detections: Table, mine, t) -> str:
    first = mine[np.argmin(t[mine])]
    return event_uuid(detections["obs_id"][first], detections["wafer_slot"][first],
                      detections["bandpass"][first], detections["scan"][first], t[first])


def _joined(values) -> str:
    return ",".join(sorted({str(v) for v in values}))


def associate_detections(detections: Table, cfg: AssociationConfig):
    """``(events, labels)``: the events table (the columns detections give; the rest are
    filled by :func:`complete_events`) and each detection's event id."""
    ra, dec = np.asarray(detections["ra"], float), np.asarray(detections["dec"], float)
    sigma = position_sigma(detections["ra_err"], detections["dec_err"])
    t = np.asarray(detections["t_peak"], float)
    far = (np.asarray(detections["far"], float) if "far" in detections.colnames
           else np.full(len(t), np.nan))
    bound = (np.asarray(detections["far_is_limit"], bool)
             if "far_is_limit" in detections.colnames else np.zeros(len(t), bool))
    labels = link(ra, dec, sigma, t, cfg)
    rows = []
    for k in range(labels.max() + 1 if len(labels) else 0):
        mine = np.flatnonzero(labels == k)
        e_ra, e_dec, e_sig = weighted_position(ra[mine], dec[mine], sigma[mine])
        bright = mine[np.argmax(np.asarray(detections["flux"])[mine])]
        rows.append(dict(event_id=k, event_uuid=_first_detection_uuid(detections, mine, t),
                         ra=np.degrees(e_ra), dec=np.degrees(e_dec),
                         pos_err=e_sig / ARCSEC, t_first=t[mine].min(), t_last=t[mine].max(),
                         n_detections=len(mine), obs_ids=_joined(detections["obs_id"][mine]),
                         wafers=_joined(detections["wafer_slot"][mine]),
                         bands=_joined(detections["bandpass"][mine]),
                         peak_flux=detections["flux"][bright],
                         peak_flux_err=detections["flux_err"][bright],
                         peak_band=detections["bandpass"][bright],
                         far=np.fmin.reduce(far[mine]),
                         far_is_limit=bool(np.isfinite(far[mine]).any()
                                           and bound[mine][np.nanargmin(far[mine])]),
                         _sigma=e_sig))
    if not rows:
        return typed_table(schema.EVENTS, {}), labels
    cols = {k: np.asarray([r[k] for r in rows]) for k in rows[0]}
    cols["source_id"] = link(np.radians(cols["ra"]), np.radians(cols["dec"]), cols.pop("_sigma"),
                             np.c_[cols["t_first"], cols["t_last"]], cfg,
                             max_gap=cfg.source_gap_hours * 3600.0)
    first_of = {}
    for k in np.argsort(cols["t_first"], kind="stable"):
        first_of.setdefault(int(cols["source_id"][k]), cols["event_uuid"][k])
    cols["source_uuid"] = [source_uuid(first_of[int(s)]) for s in cols["source_id"]]
    cols["name"] = [event_name(r, d) for r, d in zip(cols["ra"], cols["dec"])]
    cols["t_first_utc"], cols["t_last_utc"] = utc(cols["t_first"]), utc(cols["t_last"])
    return typed_table(schema.EVENTS, cols), labels


def _detected_keys(detections: Table, labels) -> set:
    return {(int(e), str(o), str(w), str(b), int(s)) for e, o, w, b, s in
            zip(labels, detections["obs_id"], detections["wafer_slot"],
                detections["bandpass"], detections["scan"])}


def lightcurve_table(units: Table, events: Table, detections: Table, labels) -> Table:
    """The ``lightcurves`` table: the units' rows with the event's position, source, UTC,
    lightcurvedb frequency, and ``detected`` where a detection of the event is at the same
    observation, wafer, band and scan."""
    if not len(units):
        return typed_table(schema.LIGHTCURVES, {})
    by_id = {int(e): i for i, e in enumerate(events["event_id"])}
    row = np.array([by_id[int(e)] for e in units["event_id"]], int)
    err_deg = events["pos_err"][row] / 3600.0
    detected = _detected_keys(detections, labels)
    keys = zip(units["event_id"], units["obs_id"], units["wafer_slot"], units["bandpass"],
               units["scan"])
    rows = {name: units[name] for name in units.colnames}
    rows.update(source_id=events["source_id"][row], time=utc(units["ctime"]),
                ra=events["ra"][row], dec=events["dec"][row], ra_uncertainty=err_deg,
                dec_uncertainty=err_deg,
                frequency=[int(str(b).lstrip("f")) for b in units["bandpass"]],
                detected=[(int(e), str(o), str(w), str(b), int(s)) in detected
                          for e, o, w, b, s in keys])
    table = typed_table(schema.LIGHTCURVES, rows)
    table.sort(["event_id", "bandpass", "ctime"])
    return table


def fit_table(lightcurves: Table, cfg: FlareFitConfig) -> Table:
    """Eq. 1 fitted to each event's light curve in each band (``lightcurve_fits``)."""
    rows = []
    for event_id in np.unique(lightcurves["event_id"]):
        mine = lightcurves[lightcurves["event_id"] == event_id]
        for band in np.unique(mine["bandpass"]):
            lc = mine[mine["bandpass"] == band]
            res = fit_flare(lc["ctime"], lc["flux"], lc["flux_err"], cfg)
            rows.append(dict(res, event_id=int(event_id), bandpass=str(band)))
    names = ["event_id", "bandpass", *[n for p in FLARE_PARAMS for n in (p, f"{p}_err")],
             "chi2_red", "n_points", "fit_ok"]
    return typed_table(schema.LIGHTCURVE_FITS,
                       {k: [r[k] for r in rows] for k in names} if rows else {})


def _simultaneous(lc: Table, band_a, band_b):
    """Pairs of crossings of one wafer and scan measured in both bands: (rows a, rows b)."""
    key = lambda r: (str(r["obs_id"]), str(r["wafer_slot"]), int(r["scan"]))
    a = {key(r): i for i, r in enumerate(lc) if r["bandpass"] == band_a}
    b = {key(r): i for i, r in enumerate(lc) if r["bandpass"] == band_b}
    common = sorted(set(a) & set(b))
    return np.array([a[k] for k in common], int), np.array([b[k] for k in common], int)


def _multiband(lc: Table, pairs, bands_detected):
    """``(joint_snr, single_band)`` of one event from its light curve; ``pairs``:
    {(band_a, band_b): :func:`_simultaneous` rows} for each wafer flavour's two bands."""
    joint, single = np.nan, False
    for (band_a, band_b), (ia, ib) in pairs.items():
        if not len(ia):
            continue
        seen = np.asarray(lc["detected"][ia], bool) | np.asarray(lc["detected"][ib], bool)
        if seen.any():
            combined = (lc["snr"][ia][seen] + lc["snr"][ib][seen]) / np.sqrt(2)
            joint = float(np.fmax(joint, np.max(combined)))
            single |= len({band_a, band_b} & set(bands_detected)) == 1
    return joint, single


def complete_events(events: Table, lightcurves: Table, min_snr) -> Table:
    """``events`` with the columns the light curves give (a new table)."""
    cols = {name: list(events[name]) for name in events.colnames}
    for i, ev in enumerate(events):
        lc = lightcurves[lightcurves["event_id"] == ev["event_id"]]
        cols["n_crossings"][i] = len(lc)
        cols["n_upper_limits"][i] = int(np.isfinite(lc["upper_limit"]).sum())
        pairs = {bands: _simultaneous(lc, *bands) for bands in FLAVOR_BANDS.values()}
        cols["joint_snr"][i], cols["single_band"][i] = _multiband(lc, pairs,
                                                                  ev["bands"].split(","))
        for ((band_a, band_b), (ia, ib)), name in zip(pairs.items(), ("alpha_mf", "alpha_uhf")):
            cols[name][i], cols[f"{name}_err"][i], _ = spectral_index(
                lc["flux"][ia], lc["flux_err"][ia], lc["flux"][ib], lc["flux_err"][ib],
                band_a, band_b, min_snr)
        cols["note"][i] = _note(lc)
    return typed_table(schema.EVENTS, cols)


def _note(lc: Table) -> str:
    """What could not be measured for an event: no crossing, or a detected band's wafer
    without its other band."""
    if not len(lc):
        return "no crossing measured in the light-curve window"
    notes = []
    for band_a, band_b in FLAVOR_BANDS.values():
        measured = set(lc["bandpass"])
        for have, miss in ((band_a, band_b), (band_b, band_a)):
            if have in measured and miss not in measured:
                notes.append(f"{miss} not measured (no {miss} group of these wafers in "
                             "the archive, or it failed)")
    return "; ".join(notes)


def crossmatch_events(events: Table, catalogue: Catalogue, ephemerides: Ephemerides | None,
                      cfg: CrossmatchConfig) -> Table:
    """``events`` with the cross-match columns (a new table): each event's position and peak
    flux against ``catalogue``, and against the solar-system objects of ``ephemerides`` at the
    middle of its detections (:func:`so_transients.sources.crossmatch.crossmatch`)."""
    cols = {name: list(events[name]) for name in events.colnames}
    cols.update(crossmatch(np.radians(np.asarray(events["ra"], float)),
                           np.radians(np.asarray(events["dec"], float)),
                           np.asarray(events["peak_flux"], float),
                           0.5 * (np.asarray(events["t_first"]) + np.asarray(events["t_last"])),
                           catalogue, ephemerides, cfg))
    return typed_table(schema.EVENTS, cols)
