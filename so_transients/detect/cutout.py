"""What a person looks at to vet a crossing: a sky cutout made from the time-ordered data,
and the time streams of the detectors that saw it.

* :func:`cutout_map`: the filtered amplitude (mJy) of every detector that passes near a
  position, in a time window around a crossing, binned into a small tangent-plane (TAN) map
  with inverse-variance weights: a map of the matched-filtered signal of that crossing alone.
  A point source appears as the beam across the scan and the filter's response along it,
  peaking at its position.
* :func:`crossing_streams`: the detectors closest to the source's path, their amplitude
  timestreams (filtered), the preprocessed signal they came from, and the beam model of a
  fitted flux over them, around the crossing.

Plain functions on :class:`~so_transients.detect.fit.FitInputs` and arrays, as the fit.
"""
from __future__ import annotations

import numpy as np
from astropy.wcs import WCS

from so_transients.common import pointing
from so_transients.common.angles import DEG
from so_transients.detect.fit import FitInputs, FitConfig, beam_shape, fit_window

#: Cutout size and pixel, in beam FWHMs of the band: ~9' across and ~0.4' pixels at f090.
CUTOUT_HALF_WIDTH_FWHM = 2.0
CUTOUT_PIXEL_FWHM = 1 / 6


def cutout_wcs(ra, dec, half_width, pixel) -> tuple[WCS, int]:
    """A TAN WCS centred on (ra, dec) (radians) with square pixels of ``pixel`` radians,
    RA increasing to the left, and the number of pixels per side (odd: the centre is a
    pixel's centre)."""
    n = 2 * int(np.ceil(half_width / pixel)) + 1
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [np.degrees(ra) % 360.0, np.degrees(dec)]
    wcs.wcs.crpix = [(n + 1) / 2, (n + 1) / 2]
    wcs.wcs.cdelt = [-np.degrees(pixel), np.degrees(pixel)]
    wcs.wcs.cunit = ["deg", "deg"]
    return wcs, n


def bin_samples(wcs: WCS, n, ra, dec, values, weights):
    """``(map, weight)``: inverse-variance weighted mean of ``values`` at sky positions
    (ra, dec) (radians) in the ``n`` x ``n`` pixels of ``wcs`` (NaN where nothing fell)."""
    x, y = wcs.all_world2pix(np.degrees(ra) % 360.0, np.degrees(dec), 0)
    ix, iy = np.round(x).astype(int), np.round(y).astype(int)
    inside = (ix >= 0) & (ix < n) & (iy >= 0) & (iy < n) & np.isfinite(values) & (weights > 0)
    pix = iy[inside] * n + ix[inside]
    w = np.bincount(pix, weights[inside], minlength=n * n)
    wv = np.bincount(pix, weights[inside] * values[inside], minlength=n * n)
    with np.errstate(invalid="ignore", divide="ignore"):
        sky = np.where(w > 0, wv / w, np.nan)
    return sky.reshape(n, n), w.reshape(n, n)


def cutout_map(data: FitInputs, ra, dec, t_center, band_dets, fit_cfg: FitConfig,
               half_width=None, pixel=None):
    """``(map, weight, wcs)`` of the crossing of (ra, dec) (radians) at ``t_center``: the
    amplitude samples (mJy) of the live detectors of ``band_dets`` that pass near the source
    (those the fit uses), over the fit's window, binned (:func:`bin_samples`) with weights
    ``1 / sigma_amp**2`` (1/mJy^2). ``half_width`` and ``pixel`` (radians) default to
    :data:`CUTOUT_HALF_WIDTH_FWHM` and :data:`CUTOUT_PIXEL_FWHM` beam FWHMs."""
    live = band_dets[~data.dead[band_dets]]
    fwhm = float(np.median(data.beam_sigma[live])) * np.sqrt(8 * np.log(2)) if len(live) \
        else 2.2 / 60 * DEG
    half_width = CUTOUT_HALF_WIDTH_FWHM * fwhm if half_width is None else half_width
    pixel = CUTOUT_PIXEL_FWHM * fwhm if pixel is None else pixel
    wcs, n = cutout_wcs(ra, dec, half_width, pixel)
    t = data.timestamps
    lo, hi = np.searchsorted(t, [t_center - fit_cfg.window, t_center + fit_cfg.window])
    if hi - lo < 2 or not len(live):
        return np.full((n, n), np.nan), np.zeros((n, n)), wcs
    _, _, dets = fit_window(data, ra, dec, lo, hi, live, fit_cfg)
    amp = data.amplitude(dets, lo, hi)
    d, s = np.meshgrid(dets, np.arange(lo, hi), indexing="ij")
    sky_ra, sky_dec = pointing.radec_of_samples(data.bore_q, data.xi, data.eta, d.ravel(),
                                                s.ravel())
    sigma = np.asarray(data.sigma_amp, float)[dets]
    with np.errstate(divide="ignore"):
        w = np.where(sigma > 0, 1.0 / sigma ** 2, 0.0)
    weights = np.broadcast_to(w[:, None], amp.shape) * (amp != 0)   # 0: not fitted there
    sky, weight = bin_samples(wcs, n, sky_ra, sky_dec, amp.ravel().astype(float),
                              weights.ravel())
    return sky, weight, wcs


def crossing_streams(data: FitInputs, signal, ra, dec, t_center, band_dets, fit_cfg: FitConfig,
                     flux, offset, half_span=1.0, n_dets=6) -> dict:
    """Around the crossing of (ra, dec) at ``t_center``: the ``n_dets`` live detectors of
    ``band_dets`` whose paths pass closest to the source, over ``t_center +- half_span`` s.
    Returns ``t`` (s from ``t_center``), ``dets`` (indices), ``across`` (their distance
    from the source's path, beam sigmas), ``filtered`` (amplitude, mJy), ``raw`` (the
    preprocessed ``signal`` they were filtered from, less its median there; NaN without
    one) and ``model`` (``flux`` x the beam through the filter + ``offset``, the beam
    fit's model)."""
    t = data.timestamps
    lo, hi = np.searchsorted(t, [t_center - half_span, t_center + half_span])
    live = band_dets[~data.dead[band_dets]]
    empty = dict(t=np.zeros(0), dets=np.zeros(0, int), across=np.zeros(0),
                 filtered=np.zeros((0, 0)), raw=np.zeros((0, 0)), model=np.zeros((0, 0)))
    if hi - lo < 2 or not len(live):
        return empty
    _, track, near = fit_window(data, ra, dec, lo, hi, live, fit_cfg)
    if not len(near):
        return empty
    mid = (hi - lo) // 2
    across = np.abs(-(data.xi[near] - track.xi[mid]) * track.along[1]
                    + (data.eta[near] - track.eta[mid]) * track.along[0]) / track.sigma
    order = np.argsort(across, kind="stable")[:n_dets]
    dets = near[order]
    shape = beam_shape(track, data.xi[dets], data.eta[dets])
    if signal is not None:
        raw = np.asarray(signal[dets, lo:hi], float)
        raw = raw - np.nanmedian(raw, axis=1, keepdims=True)
    else:
        raw = np.full((len(dets), hi - lo), np.nan)
    return dict(t=t[lo:hi] - t_center, dets=dets, across=across[order],
                filtered=data.amplitude(dets, lo, hi).astype(float), raw=raw,
                model=flux * shape + offset)
