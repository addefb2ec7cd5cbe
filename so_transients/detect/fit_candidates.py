"""A group's candidates fitted (``transient_fit``): each one's beam fit
(:func:`so_transients.detect.fit.fit_at`), or for a sweep stack the fixed-position fit of its
crossings (:func:`so_transients.detect.forced_fit.stack_fit`), then the detection decision
(:func:`detection_decision`): ``A0/sigma_A >= min_snr``, not moving, a brightest detector in
proportion, two halves of the detectors that agree (``pass_split``), ``pass_far``,
``pass_score``, and not a repeat of a detection of the same crossing
(:func:`crossing_duplicates`).
"""
from __future__ import annotations

import numpy as np

from so_transients.common import candidates
from so_transients.common.angles import ARCMIN, ARCSEC, sky_separation
from so_transients.common.bands import CENTER_GHZ, fwhm_to_sigma
from so_transients.detect.error_scale import (
    ErrorScale, Sources, measure_error_scale, measure_error_scales
)
from so_transients.detect.fit import FitConfig, FitInputs, fit_at
from so_transients.detect.forced_fit import stack_fit
from so_transients.detect.motion import flag_moving


OUTPUT_FIELDS = ("flux", "flux_err", "ra", "dec", "ra_err", "dec_err", "offset", "offset_err",
                 "snr_fit", "chi2_red", "n_fit_samples", "n_fit_dets", "fit_ok", "error_scale",
                 "split_sigma")


def fit_group_candidates(data: FitInputs, cands, det_bands, cfg: FitConfig, score=None):
    """Fit every candidate of a group that passed the cuts (all when there is no ``passed``);
    returns every ``transient_fit`` column. ``score``: a function of the candidates' columns
    (with the fit's) giving ``real_score`` and ``pass_score`` (a real-or-artefact score and
    its cut, :mod:`so_transients.score`), or None. Significant fits whose positions move from scan
    to scan are flagged ``moving`` and not ``detected``. The error scale is ``cfg.error_scale``
    or, per band and scan direction, measured at null positions clear of the candidates that
    passed the cuts (:func:`so_transients.detect.error_scale.measure_error_scales`); each
    candidate's fit takes the scale of its own sweep's direction."""
    n = len(cands["bandpass"])
    passed = np.asarray(cands.get("passed", np.ones(n, bool)), bool)
    sources = Sources.of_candidates(cands, passed)
    scales = {b: ErrorScale.of(cfg.error_scale) or measure_error_scales(
                  data, np.flatnonzero(det_bands == b), sources, cfg)
              for b in np.unique(cands["bandpass"][passed])}
    rows = [_fit_one(data, cands, c, det_bands, scales[cands["bandpass"][c]], cfg)
            if passed[c] else {} for c in range(n)]
    if cfg.local_window is not None and cfg.error_scale is None:
        _local_scales(data, cands, det_bands, scales, rows, cfg)
    schema = candidates.BY_NAME
    out = {k: np.array([r.get(k, schema[k].fill) for r in rows], dtype=schema[k].dtype)
           for k in OUTPUT_FIELDS}
    fitted = out["fit_ok"]
    out["ra"] = np.where(fitted, out["ra"], cands["cluster_ra"])
    out["dec"] = np.where(fitted, out["dec"], cands["cluster_dec"])
    out["real_score"], out["pass_score"] = np.full(n, np.nan), np.ones(n, bool)
    if score is not None and fitted.any():
        out["real_score"][fitted], out["pass_score"][fitted] = score(
            {k: np.asarray(v)[fitted] for k, v in {**cands, **out}.items()})
    out["snr_joint"] = joint_snr(cands, out)
    fwhm = {b: float(np.median(data.beam_sigma[det_bands == b])) / fwhm_to_sigma(1.0)
            for b in np.unique(cands["bandpass"])}
    out.update(detection_decision(cands, out, cfg, fwhm))
    return candidates.check(out, "transient_fit")


def _local_scales(data: FitInputs, cands, det_bands, scales, rows, cfg: FitConfig):
    """Refit, in ``rows``, each single-crossing fit significant at its band's error scale
    with the scale measured within ``cfg.local_window`` seconds of it, in sweeps of its own
    direction, when that is larger
    (:func:`so_transients.detect.error_scale.measure_error_scale` with ``around``), clear of
    every such fit.

    Why: the noise is not stationary, and a noise fluctuation is fitted significant where
    it is higher. On ten noise-only drawn wafers (docs/results/drawn_wafers.md) the spread
    of null fits within 30 s of each of the 12 fits that passed min_snr was 2-24 % above
    the observation's; at a cut of 5 that many per cent let them through."""
    single = np.asarray(cands.get("n_crossings", np.ones(len(rows), int))) == 1
    significant = [c for c, r in enumerate(rows) if r.get("fit_ok") and single[c]
                   and np.nan_to_num(r.get("snr_fit", np.nan)) >= cfg.min_snr]
    sources = Sources.of_candidates(cands, significant)
    for c in significant:
        band, direction = cands["bandpass"][c], _direction(data, cands, c)
        local = measure_error_scale(data, np.flatnonzero(det_bands == band), sources, cfg,
                                    direction, around=float(cands["t_median"][c]))
        if local > scales[band].at(direction):
            rows[c] = _fit_one(data, cands, c, det_bands,
                               scales[band].with_value(direction, local), cfg)


def detection_decision(cands, fits, cfg: FitConfig, fwhm_by_band):
    """``moving``, ``motion_rate``, ``pass_peak_ratio``, ``duplicate_of`` and ``detected`` of
    a group's fitted candidates (``fits``: their ``fit_ok``, ``snr_fit``, ``ra``, ``dec``,
    ``ra_err``, ``dec_err``, and ``pass_score`` where a score cuts; ``fwhm_by_band``: each
    band's beam FWHM, radians).

    Significant fits (``fit_ok``, ``snr_fit >= min_snr``) of one crossing are joined first
    (:func:`crossing_duplicates`), keeping the one that passes ``pass_peak_ratio``,
    ``pass_far`` and ``pass_score`` with the highest ``snr_fit``: the others are not detected, and their
    ``duplicate_of`` names its ``cand_id``. The motion test then sees one detection per
    crossing (a duplicate takes its ``moving`` and ``motion_rate``)."""
    n = len(cands["bandpass"])
    significant = fits["fit_ok"] & (np.nan_to_num(fits["snr_fit"]) >= cfg.min_snr)
    significant |= fits["fit_ok"] & jointly_significant(cands, fits, cfg.min_snr)
    out = {"pass_peak_ratio": peak_ratio_ok(cands["snr_max"], fits["snr_fit"],
                                            cfg.max_peak_ratio),
           "pass_split": split_ok(fits.get("split_sigma", np.full(n, np.nan)),
                                  cfg.max_split_sigma)}
    allowed = np.asarray(cands.get("pass_far", np.ones(n, bool)), bool) \
        & np.asarray(fits.get("pass_score", np.ones(n, bool)), bool)
    single = np.asarray(cands.get("n_crossings", np.ones(n, int))) == 1
    sel = np.flatnonzero(significant & single & (np.asarray(cands["scan"]) >= 0))
    trusted = out["pass_peak_ratio"] & out["pass_split"]
    preference = np.lexsort((-np.nan_to_num(fits["snr_fit"][sel], nan=-np.inf),
                             ~(trusted & allowed)[sel]))
    repeats = crossing_duplicates(cands["scan"][sel], cands["bandpass"][sel], fits["ra"][sel],
                                  fits["dec"][sel], preference,
                                  np.array([fwhm_by_band[b] for b in cands["bandpass"][sel]]))
    kept = np.full(n, -1)                   # the detection a duplicate repeats
    kept[sel[repeats >= 0]] = sel[repeats[repeats >= 0]]
    duplicate = kept >= 0
    moving, rate = _motion(cands, fits, significant & ~duplicate, cfg)
    moving[duplicate], rate[duplicate] = moving[kept[duplicate]], rate[kept[duplicate]]
    cand_id = np.asarray(cands.get("cand_id", np.arange(n)))
    out.update(moving=moving, motion_rate=rate,
               duplicate_of=np.where(duplicate, cand_id[kept], -1),
               detected=significant & ~moving & trusted & allowed & ~duplicate)
    return out


def jointly_significant(cands, fits, min_snr):
    """Whether each candidate is the member of a joint pair with the higher ``snr_fit``
    and the pair's ``snr_joint`` reaches ``min_snr``: one band's detection stands for the
    pair (the other is detected only on its own ``snr_fit``)."""
    n = len(cands["bandpass"])
    out = np.zeros(n, bool)
    joint = np.asarray(cands.get("joint_id", np.full(n, -1)))
    snr_joint = np.nan_to_num(np.asarray(fits.get("snr_joint", np.full(n, np.nan))))
    own = np.nan_to_num(np.asarray(fits["snr_fit"], float), nan=-np.inf)
    for j in np.unique(joint[joint >= 0]):
        sel = np.flatnonzero(joint == j)
        best = sel[np.argmax(own[sel])]
        out[best] = snr_joint[best] >= min_snr
    return out


def joint_snr(cands, fits):
    """For each candidate of a joint-band pair (``joint_id`` >= 0, both bands fitted): the
    S/N of the flux ``S_0`` that both bands' fitted fluxes ``A`` give at the pair's
    ``spectral_index`` alpha, ``r^T V^-1 A / sqrt(r^T V^-1 r)`` with ``r_b = nu_b^alpha``
    (the bands' centre frequencies) and ``V`` the fluxes' covariance: their errors and the
    bands' ``band_correlation`` (their noise shares the residual atmosphere); NaN
    otherwise."""
    n = len(cands["bandpass"])
    out = np.full(n, np.nan)
    joint = np.asarray(cands.get("joint_id", np.full(n, -1)))
    for j in np.unique(joint[joint >= 0]):
        sel = np.flatnonzero(joint == j)
        flux, err = fits["flux"][sel], fits["flux_err"][sel]
        if len(sel) < 2 or not (fits["fit_ok"][sel] & (err > 0)).all():
            continue
        nu = np.array([CENTER_GHZ[b] for b in cands["bandpass"][sel]])
        r = (nu / nu[0]) ** float(cands["spectral_index"][sel[0]])
        rho = np.nan_to_num(np.asarray(cands.get("band_correlation", np.zeros(n)))[sel[0]])
        corr = np.where(np.eye(len(sel), dtype=bool), 1.0, rho)
        weights = np.linalg.solve(corr * np.outer(err, err), r)
        out[sel] = weights @ flux / np.sqrt(weights @ r)
    return out


def crossing_duplicates(scan, bands, ra, dec, preference, radius):
    """Index of the detection each detection repeats, -1 for those it keeps.

    Detections of one scan and band whose positions (``ra``, ``dec``, radians) lie within
    ``radius`` (radians, per detection: the band's beam FWHM) are one crossing: within one
    scan the array passes over a sky position once, so the scan is the crossing's time
    window. ``preference``: the detections' indices, the one to keep first. Each detection
    not yet assigned, in that order, is kept and claims the unassigned ones of its scan and
    band within its ``radius`` (as non-maximum suppression does).

    Why: the paper clusters the S/N >= 3 samples of a scan with DBSCAN at sigma_FWHM
    (:mod:`so_transients.detect.find`), and that stays as it is. Each detector sees a
    crossing along its own track, a line along the scan; neighbouring tracks lie up to 0.86'
    apart across the scan (the simulated wafers, 1.57' pitch), depending on the angle
    between scan and array. Where a gap exceeds sigma_FWHM (0.60' at f220, 0.54' at f280;
    0.84' at f150, barely; never f090's 1.32'), a source passing between two tracks gives
    one cluster on each side: two candidates, whose beam fits use the same samples and
    converge to one position (within arcseconds; such gaps split 3 of 6 f220 crossings on
    UHF wafer w01 at elevation 60). Sources more than a beam apart stay separate, as do
    crossings in different scans.
    """
    scan, bands = np.asarray(scan), np.asarray(bands)
    ra, dec, radius = np.asarray(ra, float), np.asarray(dec, float), np.asarray(radius, float)
    repeats = np.full(len(scan), -1)
    done = np.zeros(len(scan), bool)
    for i in preference:
        if done[i]:
            continue
        done[i] = True
        same = ~done & (scan == scan[i]) & (bands == bands[i]) & (
            sky_separation(ra, dec, ra[i], dec[i]) <= radius[i])
        repeats[same], done[same] = i, True
    return repeats


def _direction(data: FitInputs, cands, c) -> int:
    """Scan direction (+1, -1) of the sweep candidate ``c`` was found in."""
    at = np.searchsorted(data.timestamps, cands["t_median"][c])
    return int(data.direction[min(at, len(data.timestamps) - 1)])


def _fit_one(data: FitInputs, cands, c, det_bands, scale: ErrorScale, cfg: FitConfig):
    """Candidate ``c``'s fit with its band's error ``scale``: :func:`fit_at` at the scale of
    its sweep's direction, or for a sweep stack (``n_crossings`` > 1) the combined
    fixed-position fit of its crossings, each at its own direction's
    (:func:`so_transients.detect.forced_fit.stack_fit`)."""
    band = cands["bandpass"][c]
    args = (data, cands["cluster_ra"][c], cands["cluster_dec"][c])
    dets = np.flatnonzero(det_bands == band)
    if int(cands.get("n_crossings", np.ones(c + 1, int))[c]) > 1:
        return stack_fit(*args, cands["t_start"][c], cands["t_stop"][c], dets, scale, cfg)
    return fit_at(*args, cands["t_median"][c], dets, scale.at(_direction(data, cands, c)), cfg)


def split_ok(split, max_split_sigma):
    """Whether the fits of two halves of each candidate's detectors agree within
    ``max_split_sigma`` errors (:func:`so_transients.detect.fit.split_sigma`; True where it
    was not measured, or without a limit)."""
    split = np.asarray(split, float)
    if max_split_sigma is None:
        return np.ones(len(split), bool)
    return ~(split > max_split_sigma)


def peak_ratio_ok(snr_max, snr_fit, max_ratio):
    """Whether each candidate's brightest detector (``snr_max``) is within ``max_ratio`` times
    its fitted S/N (all True when ``max_ratio`` is None). A source bright enough to give one
    detector S/N 40 is fitted far above S/N 40 / max_ratio over the dozens of detectors that
    cross it (injected flares: snr_max / snr_fit below 1.22 for 99.9 % of 39,241 detections,
    one above 3); a glitch residue, one detector hit hard beside a faint noise cluster, is
    not."""
    snr_max = np.asarray(snr_max, float)
    if max_ratio is None:
        return np.ones(len(snr_max), bool)
    return ~(snr_max > max_ratio * np.nan_to_num(np.asarray(snr_fit, float), nan=np.inf))


def _motion(cands, out, significant, cfg: FitConfig):
    """``moving`` and ``motion_rate`` (arcmin/min) of the significant fits, band by band
    (:func:`so_transients.detect.motion.flag_moving`)."""
    n = len(significant)
    moving, rate = np.zeros(n, bool), np.full(n, np.nan)
    per_min = ARCMIN / 60.0
    for band in np.unique(cands["bandpass"][significant]):
        sel = np.flatnonzero(significant & (cands["bandpass"] == band))
        err = np.hypot(np.hypot(out["ra_err"][sel], out["dec_err"][sel]),
                       cfg.motion_floor_arcsec * ARCSEC)
        moving[sel], r = flag_moving(cands["t_peak"][sel], out["ra"][sel], out["dec"][sel], err,
                                     cfg.max_motion_arcmin_per_min * per_min,
                                     cfg.min_motion_arcmin_per_min * per_min)
        rate[sel] = r / per_min
    return moving, rate
