"""Forced photometry of every event in one group (one wafer in one band of an observation).

A work unit of ``so-transients events``: the group is loaded from the preprocess archive with
sotodlib's ``load_and_preprocess`` (``transient_filter``'s ``process()`` rebuilds the
filtered data), each event's position is measured at every crossing of its time window
(:mod:`so_transients.detect.forced_fit`), and the rows are written to one ECSV file (with the
sky tracks of the detectors at each event's best crossing, for its figure, in an NPZ file
beside it, and for each event's best crossing in each band the sky cutout and the detector
time streams a person vets it with, :mod:`so_transients.detect.cutout`, in a third). A unit
that finished is not run again while its inputs are unchanged; a unit
that fails returns the error, naming the observation, the group and the archive.
"""
from __future__ import annotations

import hashlib
import json
import os
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from astropy.table import Table

from so_transients.common import pointing
from so_transients.detect.cutout import crossing_streams, cutout_map
from so_transients.detect.find import FindConfig, group_scans
from so_transients.detect.error_scale import ErrorScale, Sources, measure_error_scales
from so_transients.detect.fit import FitConfig, FitInputs, fit_window
from so_transients.detect.forced_fit import PhotometryConfig, group_crossings, measure_crossings
from so_transients.site.pipeline import read_config

#: Columns of a unit's ECSV file, beside the event id (all of the lightcurves table's that
#: a group knows; the rest are added when the units are combined).
UNIT_COLUMNS = ("event_id", "ctime", "scan", "flux", "flux_err", "snr", "upper_limit",
                "offset", "n_fit_dets", "chi2_red")


@dataclass
class GroupJob:
    """What one work unit needs: picklable, so it can go to a pool or an MPI rank."""

    preprocess: str                  # the site config
    obs_id: str
    tags: dict                       # the group's det_info selection, e.g. wafer_slot, bandpass
    events: list                     # dicts: event_id, ra, dec, t_lo, t_hi (rad, ctime)
    error_scale: ErrorScale | None   # the group's transient_fit error scales (None: measure)
    fit: FitConfig = field(default_factory=FitConfig)
    find: FindConfig = field(default_factory=FindConfig)
    photometry: PhotometryConfig = field(default_factory=PhotometryConfig)
    out: str = ""                    # ECSV path of the result
    archive_stamp: str = ""          # the archive file's size and mtime: a rerun of the
    #                                  site pipeline invalidates the result

    @property
    def name(self) -> str:
        return f"{self.obs_id} {'/'.join(str(v) for v in self.tags.values())}"

    def digest(self) -> str:
        """Of everything the result depends on: the settings, the events, the archive file's
        stamp and the site config's content (its process() steps rebuild the data)."""
        payload = {k: v for k, v in asdict(self).items() if k != "out"}
        payload["preprocess"] = read_config(self.preprocess)
        return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str)
                              .encode()).hexdigest()[:16]


def job_done(job: GroupJob) -> bool:
    path = Path(job.out)
    return (path.is_file() and vetting_path(path).is_file()
            and Table.read(path).meta.get("digest") == job.digest())


def run_job(job: GroupJob) -> dict:
    """Run one unit (or reuse its earlier result); returns ``{obs_id, group, path, error}``
    with ``error`` '' when it worked, else the error type and message."""
    status = dict(obs_id=job.obs_id, group="/".join(str(v) for v in job.tags.values()),
                  path=job.out, error="")
    if job_done(job):
        return status
    try:
        table, tracks, vetting = measure_group(job)
    except Exception as exc:          # recorded per unit; the other units go on
        status["error"] = f"{type(exc).__name__}: {exc}"
        status["traceback"] = traceback.format_exc()
        return status
    table.meta.update(digest=job.digest(), obs_id=job.obs_id, tags=dict(job.tags))
    out = Path(job.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # the tracks and cutouts first, and each file complete before it gets its name: an
    # interrupted unit never looks finished
    for arrays, path in ((tracks, tracks_path(out)), (vetting, vetting_path(out))):
        partial = path.with_name(path.name + ".partial.npz")
        np.savez_compressed(partial, **arrays)
        os.replace(partial, path)
    partial = out.with_name(out.name + ".partial")
    table.write(partial, format="ascii.ecsv", overwrite=True)
    os.replace(partial, out)
    return status


def tracks_path(unit_path) -> Path:
    return Path(unit_path).with_suffix(".tracks.npz")


def vetting_path(unit_path) -> Path:
    """The unit's cutouts and time streams: ``<event_id>_<band>_<name>`` arrays
    (:func:`vetting_arrays`)."""
    return Path(unit_path).with_suffix(".vetting.npz")


def read_vetting(path) -> dict:
    """{(event_id, band): {name: array}} of a unit's :func:`vetting_path` file."""
    out = {}
    with np.load(path) as held:
        for key in held.files:
            eid, band, name = key.split("_", 2)
            out.setdefault((int(eid), band), {})[name] = held[key]
    return out


def load_group(job: GroupJob):
    """The group's AxisManager as the site pipeline's ``process()`` steps leave it."""
    from sotodlib.preprocess.preprocess_util import load_and_preprocess

    where = f"{job.name} (archive of {job.preprocess})"
    try:
        # the config as a dict with its paths resolved (they may be relative to its folder)
        loaded = load_and_preprocess(job.obs_id, read_config(job.preprocess),
                                     dets=dict(job.tags))
    except Exception as exc:
        raise RuntimeError(f"{where}: cannot load and preprocess: {exc}") from exc
    if loaded is None or loaded[0] is None:
        raise ValueError(f"{where}: no detector left after the archive's cuts")
    aman = loaded[0]
    if "transient_snr" not in aman._fields:
        raise ValueError(f"{where}: transient_filter did not run (not in process_pipe?)")
    return aman


def module_of(aman) -> str:
    """The group's optics tube (det_info tube_slot), '' when the metadata do not say."""
    info = aman.det_info if "det_info" in aman._fields else None
    if info is not None and "tube_slot" in info._fields and aman.dets.count:
        return str(np.asarray(info.tube_slot)[0])
    return ""


def measure_group(job: GroupJob):
    """``(table, tracks, vetting)``: the forced photometry of every event of ``job`` at every
    crossing of the group, and for each event the detector tracks of its best crossing and
    what a person vets it with there (:func:`vetting_arrays`)."""
    aman = load_group(job)
    signal = aman.signal if "signal" in aman._fields else None
    names = np.asarray(aman.dets.vals).astype(str)
    data = FitInputs.from_aman(aman, speed_tolerance=job.find.speed_tolerance)
    scan, _ = group_scans(aman.timestamps, aman.boresight.az, aman.boresight.el, job.find,
                          job.name)
    bands = np.asarray(aman.transient_filter.bandpass).astype(str)
    wafers = (np.asarray(aman.det_info.wafer_slot).astype(str)
              if "wafer_slot" in aman.det_info._fields else np.full(aman.dets.count, ""))
    rows, tracks, vetting = [], {}, {}
    for band in np.unique(bands):
        band_dets = np.flatnonzero(bands == band)
        reach = 3 * float(np.median(data.beam_sigma[band_dets]))
        crossings = [group_crossings(data, scan, ev["ra"], ev["dec"], ev["t_lo"], ev["t_hi"],
                                     band_dets, reach) for ev in job.events]
        # transient_fit's scales for this group, else its fixed one, else measured as it
        # measures them, clear of every crossing of the events
        sources = Sources.join(Sources.at(c[0], ev["ra"], ev["dec"])
                               for c, ev in zip(crossings, job.events))
        scale = job.error_scale or ErrorScale.of(job.fit.error_scale) or measure_error_scales(
            data, band_dets, sources, job.fit)
        for ev, (times, scans) in zip(job.events, crossings):
            res = measure_crossings(data, ev["ra"], ev["dec"], times, band_dets, scale,
                                    job.fit, job.photometry)
            keep = res.pop("keep")
            if not keep.any():
                continue
            n = int(keep.sum())
            rows.append(dict(res, event_id=np.full(n, ev["event_id"]), ctime=times[keep],
                             scan=scans[keep], bandpass=np.full(n, band),
                             wafer_slot=np.full(n, wafers[band_dets[0]])))
            k = int(np.argmax(res["snr"]))
            best = times[keep][k]
            tracks[f"{ev['event_id']}_{band}"] = detector_tracks(data, ev["ra"], ev["dec"],
                                                                 best, band_dets, job.fit)
            vetting.update(vetting_arrays(data, ev, band, best, band_dets, job.fit,
                                          res["flux"][k], res["snr"][k], job.obs_id,
                                          wafers[band_dets[0]]))
            vetting.update(crossings_streams(data, signal, names, ev, band, times[keep], res,
                                             band_dets, job.fit, job.photometry.detect_snr))
    table = Table({k: np.concatenate([r[k] for r in rows]) for k in rows[0]}) if rows \
        else Table({k: np.zeros(0) for k in UNIT_COLUMNS + ("bandpass", "wafer_slot")})
    table["obs_id"] = np.full(len(table), job.obs_id)
    table["module"] = np.full(len(table), module_of(aman))
    return table, tracks, vetting


def vetting_arrays(data: FitInputs, event, band, t_best, band_dets, fit_cfg, flux, snr,
                   obs_id, wafer) -> dict:
    """The cutout (``map``, ``weight``, ``wcs``: its FITS header as text) of ``event`` at its
    best crossing ``t_best`` in ``band``, keyed ``<event_id>_<band>_<name>``; ``ctime``,
    ``flux`` and ``snr`` (the forced fit's, mJy), ``obs_id`` and ``wafer_slot`` say which
    crossing, ``beam_fwhm`` (arcmin) the band's beam."""
    sky, weight, wcs = cutout_map(data, event["ra"], event["dec"], t_best, band_dets, fit_cfg)
    fwhm = float(np.median(data.beam_sigma[band_dets])) * np.sqrt(8 * np.log(2))
    arrays = dict(map=sky.astype(np.float32), weight=weight.astype(np.float32),
                  beam_fwhm=np.array(np.degrees(fwhm) * 60.0),
                  wcs=np.array(wcs.to_header_string()), ctime=np.array(t_best),
                  flux=np.array(flux), snr=np.array(snr), obs_id=np.array(obs_id),
                  wafer_slot=np.array(wafer))
    return {f"{event['event_id']}_{band}_{name}": value for name, value in arrays.items()}


#: Crossings of an event per band whose time streams are kept (the highest forced S/N first).
MAX_STREAM_CROSSINGS = 6


def crossings_streams(data: FitInputs, signal, names, event, band, times, res, band_dets,
                      fit_cfg, min_snr) -> dict:
    """The detector time streams (:func:`so_transients.detect.cutout.crossing_streams`) of
    each crossing of ``event`` in ``band`` measured at forced S/N ``min_snr`` or more (at
    least the best one; at most :data:`MAX_STREAM_CROSSINGS`), keyed
    ``<event_id>_<band>_c<k>_<name>`` in time order, with ``ctime`` and ``snr``."""
    snr = np.asarray(res["snr"], float)
    chosen = [int(i) for i in np.argsort(-snr, kind="stable")
              if snr[i] >= min_snr][:MAX_STREAM_CROSSINGS] or [int(np.argmax(snr))]
    out = {}
    for k, i in enumerate(sorted(chosen, key=lambda i: times[i])):
        streams = crossing_streams(data, signal, event["ra"], event["dec"], times[i],
                                   band_dets, fit_cfg, res["flux"][i], res["offset"][i])
        arrays = dict(streams, det_names=names[streams["dets"]], ctime=np.array(times[i]),
                      snr=np.array(snr[i]))
        out.update({f"{event['event_id']}_{band}_c{k}_{name}": value
                    for name, value in arrays.items()})
    return out


def detector_tracks(data: FitInputs, ra, dec, t_center, band_dets, fit_cfg: FitConfig,
                    n_points=25, max_dets=60):
    """Sky tracks (2, ndet, n_points) in radians (RA, Dec) of the detectors a forced fit at
    ``t_center`` uses, over its window: what the event figure draws under the position."""
    t = data.timestamps
    lo, hi = np.searchsorted(t, [t_center - fit_cfg.window, t_center + fit_cfg.window])
    live = band_dets[~data.dead[band_dets]]
    _, _, dets = fit_window(data, ra, dec, lo, hi, live, fit_cfg)
    dets = dets[:: max(1, len(dets) // max_dets)]
    samples = np.linspace(lo, max(hi - 1, lo), n_points).astype(int)
    d, s = np.meshgrid(dets, samples, indexing="ij")
    track_ra, track_dec = pointing.radec_of_samples(data.bore_q, data.xi, data.eta, d.ravel(),
                                                    s.ravel())
    return np.stack([track_ra.reshape(d.shape), track_dec.reshape(d.shape)])
