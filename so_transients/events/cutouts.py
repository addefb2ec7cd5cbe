"""The events' sky cutouts and detector time streams, from the work units to the events folder.

Each work unit keeps, for every event's best crossing in its group, a cutout made from the
TOD and the time streams of the detectors closest to the source
(:func:`so_transients.events.group_photometry.vetting_arrays`). Per event and band the
crossing with the highest forced S/N is kept and written::

    cutouts/event_<id>_<band>.fits     the binned filtered amplitude (mJy, BUNIT) with its
                                       TAN WCS; HDU WEIGHT its weights (1/mJy^2)
    cutouts/event_<id>_<band>.npz      the detector time streams of its crossings (those at
                                       the forced photometry's detection S/N, at least the
                                       best one): ``c<k>_<name>``, :func:`crossings_of`
    cutouts.ecsv                       one row per file pair (:data:`schema.CUTOUTS`)

:func:`lightcurvedb_cutout` turns a row into lightcurvedb's ``Cutout`` fields.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS

from so_transients.common.angles import sky_separation
from so_transients.common.candidates import typed_table
from so_transients.events import schema
from so_transients.events.group_photometry import read_vetting, vetting_path
from so_transients.common.times import utc

FOLDER = "cutouts"
#: The arrays of each crossing's detector time streams (``c<k>_<name>`` in the NPZ file).
STREAMS = ("t", "dets", "det_names", "across", "filtered", "raw", "model", "ctime", "snr")


def crossings_of(arrays) -> list:
    """[{name: array}] of each crossing's time streams in ``arrays`` (keys ``c<k>_<name>``),
    in time order."""
    crossings = {}
    for key, value in arrays.items():
        head, _, name = key.partition("_")
        if head[:1] == "c" and head[1:].isdigit() and name in STREAMS:
            crossings.setdefault(int(head[1:]), {})[name] = value
    return [crossings[k] for k in sorted(crossings)]


def best_crossings(statuses) -> dict:
    """{(event_id, band): arrays} of the finished units, the crossing of highest forced S/N
    where several groups saw an event in one band."""
    best = {}
    for s in statuses:
        path = vetting_path(s["path"])
        if s["error"] or not path.is_file():
            continue
        for key, arrays in read_vetting(path).items():
            if key not in best or float(arrays["snr"]) > float(best[key]["snr"]):
                best[key] = arrays
    return best


def cutout_hdus(arrays, event) -> fits.HDUList:
    """The cutout of one event and band as FITS: the map (mJy) with its WCS and what it is
    of in the header, its weights in HDU WEIGHT."""
    header = WCS(fits.Header.fromstring(str(arrays["wcs"]))).to_header()
    header["BUNIT"] = ("mJy", "filtered amplitude, inverse-variance weighted")
    header["EVENT_ID"] = (int(event["event_id"]), "so-transients events: event_id")
    header["EVUUID"] = (str(event["event_uuid"]), "event UUID (alerts, database)")
    header["SRCUUID"] = (str(event["source_uuid"]), "source UUID")
    header["OBS_ID"] = str(arrays["obs_id"])
    header["WAFER"] = str(arrays["wafer_slot"])
    header["CTIME"] = (float(arrays["ctime"]), "crossing centre, unix s")
    header["DATE-OBS"] = str(utc(float(arrays["ctime"]))[0])
    header["FLUX"] = (float(arrays["flux"]), "forced flux at this crossing, mJy")
    header["SNR"] = (float(arrays["snr"]), "its S/N")
    header["BMAJ"] = (float(arrays["beam_fwhm"]) / 60.0, "beam FWHM, deg")
    header["BMIN"] = (float(arrays["beam_fwhm"]) / 60.0, "beam FWHM, deg")
    header["EV_RA"] = (float(event["ra"]), "event RA, deg")
    header["EV_DEC"] = (float(event["dec"]), "event Dec, deg")
    primary = fits.PrimaryHDU(np.asarray(arrays["map"], np.float32), header=header)
    weight = fits.ImageHDU(np.asarray(arrays["weight"], np.float32), header=header.copy(),
                           name="WEIGHT")
    weight.header["BUNIT"] = "1/mJy^2"
    return fits.HDUList([primary, weight])


def peak_position(sky, wcs: WCS) -> tuple:
    """RA, Dec (deg) of the brightest finite pixel of ``sky`` (NaN, NaN if none)."""
    if not np.isfinite(sky).any():
        return np.nan, np.nan
    iy, ix = np.unravel_index(np.nanargmax(sky), sky.shape)
    ra, dec = wcs.all_pix2world([[ix, iy]], 0)[0]
    return float(ra), float(dec)


def write_cutouts(events: Table, statuses, out: Path) -> Table:
    """Every event's cutouts and time streams into ``out``/cutouts, and their table
    (:data:`schema.CUTOUTS`, also written as ``out``/cutouts.ecsv by the caller)."""
    folder = Path(out) / FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    by_id = {int(e["event_id"]): e for e in events}
    rows = []
    for (eid, band), arrays in sorted(best_crossings(statuses).items()):
        event = by_id.get(eid)
        if event is None:
            continue
        stem = f"event_{eid:04d}_{band}"
        cutout_hdus(arrays, event).writeto(folder / f"{stem}.fits", overwrite=True)
        np.savez_compressed(folder / f"{stem}.npz", **{
            f"c{k}_{name}": value for k, crossing in enumerate(crossings_of(arrays))
            for name, value in crossing.items()})
        ra, dec = peak_position(np.asarray(arrays["map"]),
                                WCS(fits.Header.fromstring(str(arrays["wcs"]))))
        offset = np.degrees(sky_separation(*np.radians([ra, dec, event["ra"], event["dec"]])))
        rows.append(dict(event_id=eid, event_uuid=event["event_uuid"],
                         source_uuid=event["source_uuid"], bandpass=band,
                         obs_id=str(arrays["obs_id"]), wafer_slot=str(arrays["wafer_slot"]),
                         ctime=float(arrays["ctime"]), time=utc(float(arrays["ctime"]))[0],
                         frequency=int(band.lstrip("f")), flux=float(arrays["flux"]),
                         snr=float(arrays["snr"]), beam_fwhm=float(arrays["beam_fwhm"]),
                         peak_ra=ra, peak_dec=dec,
                         peak_offset=offset * 60.0, file=f"{FOLDER}/{stem}.fits",
                         streams=f"{FOLDER}/{stem}.npz"))
    cols = {k: [r[k] for r in rows] for k in rows[0]} if rows else {}
    return typed_table(schema.CUTOUTS, cols)


def lightcurvedb_cutout(row, folder, module="", source_uuid=None, measurement_id=None) -> dict:
    """The fields of lightcurvedb's ``Cutout`` of one :data:`schema.CUTOUTS` row whose files
    are in ``folder`` (the events folder): ``data`` in Jy as its flux measurements are, with
    pixels nothing fell in as 0 (its model takes no NaN)."""
    data = fits.getdata(Path(folder) / str(row["file"]), ext=0).astype(float) / 1000.0
    return dict(measurement_id=measurement_id, data=np.nan_to_num(data).tolist(),
                time=str(row["time"]), units="Jy", frequency=int(row["frequency"]),
                module=str(module), source_id=source_uuid)
