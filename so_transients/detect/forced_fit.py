"""Forced photometry: the flux at a fixed sky position in every crossing of a group.

A group (one wafer in one band) sees a sky position once per sweep, when the scan carries
the position across the wafer's detectors. :func:`group_crossings` lists those crossings in a
time interval (one per scan, centred where the position passes nearest the wafer's centre),
and :func:`measure_crossings` fits the beam model ``A0 B + C`` with the position held
(:func:`so_transients.detect.fit.fit_fixed_position`) on the same window and detectors the
detection fit uses (:func:`so_transients.detect.fit.fit_window`), with the error scale measured on
the group as ``transient_fit`` measures it. A crossing whose fitted S/N stays below
``detect_snr`` gets an upper limit ``max(flux, 0) + upper_limit_sigma x flux_err``.

The inputs are :class:`so_transients.detect.fit.FitInputs`: what ``transient_filter``'s
``process()`` rebuilds when an observation is loaded from the preprocess archive.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from so_transients.common import pointing
from so_transients.common.step_config import setting
from so_transients.detect.error_scale import ErrorScale
from so_transients.detect.fit import (
    FitConfig, FitInputs, fit_fixed_position, fit_window, window_arrays
)


@dataclass
class PhotometryConfig:
    before_s: float = setting(60.0, "s", "light curve from this long before the first detection ...")
    after_s: float = setting(60.0, "s", "... to this long after the last one")
    detect_snr: float = setting(5.0, "", "below this fitted S/N a crossing gets an upper limit")
    upper_limit_sigma: float = setting(3.0, "", "upper limit: max(flux, 0) + this many flux_err")
    min_dets: int = setting(3, "", "a crossing fitted on fewer detectors is not a crossing")


#: Columns :func:`measure_crossings` returns, one value per crossing.
CROSSING_FIELDS = ("t_center", "scan", "flux", "flux_err", "offset", "snr", "upper_limit",
                   "n_fit_dets", "chi2_red")


def footprint(data: FitInputs, dets):
    """(centre (xi, eta), radius) of detectors ``dets`` in the focal plane (radians)."""
    xi, eta = data.xi[dets], data.eta[dets]
    centre = (float(np.median(xi)), float(np.median(eta)))
    radius = float(np.max(pointing.angular_distance_xieta(xi, eta, *centre), initial=0.0))
    return centre, radius


def group_crossings(data: FitInputs, scan, ra, dec, t_lo, t_hi, dets, reach):
    """Crossings of (ra, dec) by detectors ``dets`` between ctimes ``t_lo`` and ``t_hi``:
    ``(t_center, scan)`` arrays, one per searched scan (``scan`` >= 0, as ``transient_find``
    numbers them) in which the position comes within the detectors' footprint plus
    ``reach``; each at the sample where it passes nearest the footprint's centre."""
    t = data.timestamps
    lo, hi = np.searchsorted(t, [t_lo, t_hi])
    centre, radius = footprint(data, dets)
    samples, xi, eta = pointing.source_near(data.bore_q[lo:hi], ra, dec, centre, radius + reach)
    samples = samples + lo
    keep = scan[samples] >= 0
    samples, xi, eta = samples[keep], xi[keep], eta[keep]
    dist = pointing.angular_distance_xieta(xi, eta, *centre)
    times, scans = [], []
    for s in np.unique(scan[samples]):
        mine = np.flatnonzero(scan[samples] == s)
        times.append(t[samples[mine[np.argmin(dist[mine])]]])
        scans.append(int(s))
    return np.asarray(times, float), np.asarray(scans, int)


def measure_crossings(data: FitInputs, ra, dec, times, band_dets, error_scale,
                      fit_cfg: FitConfig, cfg: PhotometryConfig) -> dict:
    """Forced photometry of (ra, dec) at each crossing centred at ``times`` on the live
    detectors of ``band_dets``: a dict of :data:`CROSSING_FIELDS` arrays (``t_center`` and
    ``scan`` excepted) for the crossings fitted on at least ``cfg.min_dets`` detectors, and
    ``keep``, the mask of those crossings. ``error_scale``: an
    :class:`~so_transients.detect.error_scale.ErrorScale` (each crossing takes its sweep's
    direction's) or one number for both."""
    t = data.timestamps
    scale = ErrorScale.of(error_scale)
    live = band_dets[~data.dead[band_dets]]
    inflation = data.kernel(live)[1]
    rows = []
    for t_center in times:
        lo, hi = np.searchsorted(t, [t_center - fit_cfg.window, t_center + fit_cfg.window])
        if hi - lo < 4 or not len(live):
            rows.append(None)
            continue
        _, track, dets = fit_window(data, ra, dec, lo, hi, live, fit_cfg)
        res = fit_fixed_position(*window_arrays(data, track, dets, lo, hi), inflation,
                                 scale.at(data.direction[(lo + hi) // 2]))
        rows.append(res if res["fit_ok"] and res["n_fit_dets"] >= cfg.min_dets else None)
    keep = np.array([r is not None for r in rows], bool)
    rows = [r for r in rows if r is not None]
    flux = np.array([r["flux"] for r in rows], float)
    err = np.array([r["flux_err"] for r in rows], float)
    snr = flux / err
    limit = np.where(snr < cfg.detect_snr, np.maximum(flux, 0) + cfg.upper_limit_sigma * err,
                     np.nan)
    return dict(keep=keep, flux=flux, flux_err=err, snr=snr, upper_limit=limit,
                offset=np.array([r["offset"] for r in rows], float),
                n_fit_dets=np.array([r["n_fit_dets"] for r in rows], int),
                chi2_red=np.array([r["chi2_red"] for r in rows], float))


def stack_fit(data: FitInputs, ra, dec, t_lo, t_hi, band_dets, error_scale,
              fit_cfg: FitConfig) -> dict:
    """The fit of a sweep stack (``transient_find``'s coherent mode with ``stack_window``):
    the beam model with the position held at (ra, dec) on each crossing between ``t_lo``
    and ``t_hi`` (:func:`measure_crossings`), combined with inverse-variance weights into
    one flux, as the stack assumes a flux steady over its crossings. ``fit_ok`` needs two
    crossings fitted; the position is the stack's, with the error of a beam centroid at the
    combined S/N (sqrt(2) beam sigma / S/N per axis); no single ``offset`` (each crossing
    has its own); each crossing's errors at its sweep direction's ``error_scale``, and the
    larger of the two as the stack's ``error_scale``. Some of
    :data:`so_transients.detect.fit_candidates.OUTPUT_FIELDS` (the rest: their fill)."""
    if data.scan is None:
        raise ValueError("a sweep stack's fit needs transient_find's scan index "
                         "(aman.transient_scan): run transient_find first")
    live = band_dets[~data.dead[band_dets]]
    beam = float(np.median(data.beam_sigma[live])) if len(live) else np.nan
    times, _ = group_crossings(data, data.scan, ra, dec, t_lo - fit_cfg.window,
                               t_hi + fit_cfg.window, live, 2 * beam)
    res = measure_crossings(data, ra, dec, times, band_dets, error_scale, fit_cfg,
                            PhotometryConfig())
    out = dict(ra=float(ra), dec=float(dec), n_fit_dets=int(res["n_fit_dets"].sum()),
               error_scale=ErrorScale.of(error_scale).largest, fit_ok=len(res["flux"]) >= 2)
    if not out["fit_ok"]:
        return out
    w = 1.0 / res["flux_err"] ** 2
    flux, err = float(np.sum(w * res["flux"]) / np.sum(w)), float(1.0 / np.sqrt(np.sum(w)))
    pos_err = np.sqrt(2.0) * beam / max(abs(flux) / err, 1.0)
    out.update(flux=flux, flux_err=err, snr_fit=flux / err,
               chi2_red=float(np.mean(res["chi2_red"])), dec_err=pos_err,
               ra_err=pos_err / np.cos(dec))
    return out
