"""Simulated runs of ``so-transients events`` at the table level, for the database's tests and
load benchmark: detections of flares at given positions and times, joined into events, light
curves and fits by the events' own functions (:mod:`so_transients.events.tables`), in the
files' layout (:func:`write_run`). No time-ordered data: for the whole chain use the simulator,
the site pipeline and ``so-transients events``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.table import Table

from so_transients.common import candidates
from so_transients.common.angles import ARCSEC, DEG
from so_transients.database.runs import FILES, Run
from so_transients.events.association import AssociationConfig
from so_transients.events.command import write
from so_transients.events.lightcurve_fit import FlareFitConfig
from so_transients.events.tables import (
    associate_detections, complete_events, fit_table, lightcurve_table
)
from so_transients.site.provenance import provenance
from so_transients.site.results import write_table

BANDS = ("f090", "f150")
SWEEP_S = 12.0           # time between crossings of a position
POS_ERR_ARCSEC = 3.0     # one-axis position error of a detection
FLUX_ERR_MJY = 40.0      # error of a crossing's flux


@dataclass
class Flare:
    """A flare seen by the observation: position (deg), the scan of its first detection,
    peak flux (mJy) and the number of crossings it is detected at."""
    ra: float
    dec: float
    scan: int
    flux: float = 1000.0
    n_detected: int = 2


def simulated_run(observations, seed=0, fit=True, folder="") -> Run:
    """A :class:`~so_transients.database.runs.Run` of ``observations``: a list of
    ``(obs_id, start ctime, [Flare, ...])``. Each flare is detected in both MF bands at
    ``n_detected`` consecutive crossings, with light-curve points from 5 crossings before to 5
    after; ``fit``: eq. 1 fitted per event and band (slower), else the fits table is empty."""
    rng = np.random.default_rng(seed)
    dets, units = [], []
    for obs_id, start, flares in observations:
        for flare in flares:
            first = len(dets)
            for band in BANDS:
                for k in range(-5, flare.n_detected + 5):
                    scan = flare.scan + k
                    seen = 0 <= k < flare.n_detected
                    t = start + SWEEP_S * scan + rng.uniform(0, 1)
                    flux = (flare.flux if seen else 0.0) + rng.normal(0, FLUX_ERR_MJY)
                    units.append(dict(obs_id=obs_id, wafer_slot="w16", bandpass=band, scan=scan,
                                      ctime=t, flux=flux, flux_err=FLUX_ERR_MJY, module="i1",
                                      offset=0.0, n_fit_dets=200, chi2_red=1.0, _det=first))
                    if seen:
                        dets.append(dict(obs_id=obs_id, wafer_slot="w16", bandpass=band,
                                         scan=scan, t_peak=t, flux=flux,
                                         flux_err=FLUX_ERR_MJY, snr_fit=flux / FLUX_ERR_MJY,
                                         ra=(flare.ra + rng.normal(0, POS_ERR_ARCSEC / 3600)
                                             / np.cos(np.radians(flare.dec))) * DEG,
                                         dec=(flare.dec + rng.normal(0, POS_ERR_ARCSEC / 3600))
                                         * DEG, ra_err=POS_ERR_ARCSEC * ARCSEC,
                                         dec_err=POS_ERR_ARCSEC * ARCSEC, detected=True,
                                         fit_ok=True, passed=True, cand_id=len(dets)))
    cols = {k: np.asarray([d[k] for d in dets]) for k in dets[0]} if dets else {}
    detections = candidates.table(cols or {"obs_id": np.zeros(0, str)}, first=("obs_id",))
    events, labels = associate_detections(detections, AssociationConfig())
    units_table = _units(units, events, detections, labels)
    lightcurves = lightcurve_table(units_table, events, detections, labels)
    fits = fit_table(lightcurves if fit else lightcurves[:0], FlareFitConfig())
    events = complete_events(events, lightcurves, 3.0)
    obs_ids = [o[0] for o in observations]
    prov = provenance(None, obs_ids)
    for table in (events, lightcurves, fits):
        table.meta["provenance"] = prov
    return Run(events, lightcurves, fits, detections, labels, sorted(obs_ids), prov, folder)


def _units(units, events, detections, labels) -> Table:
    """The forced-photometry rows, each given the event of its flare's first detection."""
    rows = []
    for u in units:
        first = u.pop("_det")
        if first < len(detections):
            snr = u["flux"] / u["flux_err"]
            rows.append(dict(u, event_id=int(labels[first]), snr=snr,
                             upper_limit=max(u["flux"], 0) + 3 * u["flux_err"] if snr < 5
                             else np.nan))
    names = ["event_id", "obs_id", "wafer_slot", "bandpass", "scan", "ctime", "flux", "flux_err",
             "snr", "upper_limit", "offset", "n_fit_dets", "chi2_red", "module"]
    return Table({k: [r[k] for r in rows] for k in names}) if rows else Table()


def write_run(run: Run, folder) -> Path:
    """The run's files in ``folder`` (events, light curves, fits, and ``detections.ecsv`` as
    ``so-transients catalog`` writes it); returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for key, table in (("events", run.events), ("lightcurves", run.lightcurves),
                       ("fits", run.fits)):
        write(table, folder / FILES[key], run.provenance)
    write_table(run.detections, folder / "detections.ecsv", obs_ids=run.obs_ids,
                overwrite=True)
    return folder
