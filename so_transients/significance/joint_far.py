"""The joint-band statistic's false-alarm rate: its background from time slides and from the
sign-inverted data, as :mod:`so_transients.significance.far` makes a single band's.

For each scan, both bands' maps are made on shared positions
(:mod:`so_transients.coherent.joint`) and combined into ``J``, the highest ``J_alpha`` over the
spectral indices. The background is the same statistic made of

- the sign-inverted data (every band's S/N negated: noise with every correlation between
  detectors and between bands kept, and no source), its local maxima from
  ``background_floor`` over the data's live time, bright sources' filter sidelobes left out;
- ``n_slides`` time slides, the detectors slid in random groups
  (:mod:`so_transients.significance.slide_groups`, each band's bright maxima gated out
  first), a pixel's detectors of both bands alike, so that the slides keep the bands'
  correlation; its local maxima from ``slide_floor`` over ``n_slides`` times the scan.

Both are taken at their own index, so the trials the maximum over indices adds are
counted. Maxima one detector makes more than ``max_single_share`` of are left out of both,
as of the data's candidates (:func:`so_transients.coherent.joint.joint_shares`). The
chi-squared test is not applied to the joint statistic. The result is a
:class:`so_transients.significance.far.Background` in units of ``J``: its ``far`` and
``threshold`` read as a single band's, per hour of the wafer (both bands).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from so_transients.coherent.joint import (
    DEFAULT_INDICES, BandMap, BandScan, band_map, band_scans, joint_map, joint_rows,
    joint_shares, map_coefficients
)
from so_transients.coherent.sweep_stack import map_cell
from so_transients.common.bands import FLAVOR_BANDS
from so_transients.common.candidates import BY_NAME
from so_transients.coherent.statistic import (
    fill_edges, local_maxima, measured_scale, window_max
)
from so_transients.significance.far import (
    Background, SignificanceConfig, cyclic_map, gated_sources, significance_by_band
)
from so_transients.significance.slide_groups import group_offsets, scan_groups
from so_transients.significance.slide_maxima import SlideSearch


@dataclass
class JointScan:
    """One scan's joint statistic: the data's map ``j`` (and the ``best`` index of each
    position, into ``indices``), the bands' maps and scans it was made of, and its
    background maxima (values of ``J``) with their live seconds."""

    first: int
    rows: np.ndarray
    scans: list
    maps: list
    coefficients: np.ndarray
    j: np.ndarray
    best: np.ndarray
    window: int
    indices: tuple = DEFAULT_INDICES
    inverted: np.ndarray = field(default_factory=lambda: np.zeros(0))
    data_live_s: float = 0.0
    slides: list = field(default_factory=list)
    live_s: float = 0.0
    slide_correlation: np.ndarray | None = None    # the bands' correlation in the slides


def scan_window(scans) -> int:
    """Samples of a local maximum's neighbourhood along the scan: the widest band's beam
    crossing time."""
    return max(s.geometry.crossing_samples(s.beam_sigma) for s in scans)


def joint_scan(scans, first, cfg: SignificanceConfig, rng, indices=DEFAULT_INDICES,
               max_single_share=0.5) -> JointScan:
    """The :class:`JointScan` of one scan's bands (``scans``: :class:`BandScan`, sharing
    their drift, :func:`so_transients.coherent.joint.joint_geometries`), starting at group
    sample ``first``; ``cfg``'s ``n_slides`` time slides (0: none)."""
    rows = joint_rows(scans, cfg.row_step)
    window = scan_window(scans)
    cyclic, partial, slid, maps = [], [], [], []
    partners = pixel_partners(scans)
    fs = scans[0].geometry.sample_rate
    min_shift = int(cfg.min_slide_s * fs)
    first_groups = scan_groups(scans[0].live, cfg.slide_groups, scans[0].snr.shape[1],
                               min_shift, window, rng)
    for s, partner in zip(scans, partners):
        groups = None if first_groups is None else first_groups[partner]
        if groups is not None and len(np.unique(groups)) < int(first_groups.max()) + 1:
            groups = None       # a group without this band's detectors: each its own term
        weights, norm = s.weights(rows)
        c, p = cyclic_map(s.snr, s.geometry, rows, s.beam_sigma, s.sigma_amp, s.live, weights,
                          norm, groups)
        cyclic.append(c)
        partial.append(p)
        slid.append(groups)
        maps.append(band_map(s, rows, fill_edges(c.astype(np.float64), s.snr, weights, norm,
                                                 s.geometry.lag_samples)))
    coefficients, _ = map_coefficients([s.band for s in scans], maps, indices)
    j, best = joint_map(np.stack([m.z for m in maps]), coefficients)
    out = JointScan(first, rows, scans, maps, coefficients, j, best, window, tuple(indices))
    out.data_live_s = np.any(np.isfinite(j), axis=0).sum() / fs
    out.inverted = _inverted_maxima(out, cfg, max_single_share)
    nsamp = j.shape[1]
    if cfg.n_slides and nsamp > 2 * min_shift + 1:
        _slide(out, cyclic, partial, slid, partners, cfg, rng, min_shift, max_single_share)
    return out


def pixel_partners(scans) -> list:
    """Per band, each detector's partner among the first band's: itself in the first band,
    in the others the nearest on the focal plane not taken yet (its pixel's, in a dichroic
    wafer; a pixel's two polarizations take one each), else the nearest. Slides shift
    partners alike, so that they keep the bands' correlation (the same residual
    atmosphere) as the data have it, while within a band no two detectors slide together
    that a single band's slides would not."""
    first = scans[0].geometry
    tree = cKDTree(np.c_[first.along, first.across])
    out = [np.arange(len(first.along))]
    for s in scans[1:]:
        k = min(8, len(first.along))
        _, near = tree.query(np.c_[s.geometry.along, s.geometry.across], k=k)
        near = near.reshape(len(s.geometry.along), k)
        taken = np.zeros(len(first.along), bool)
        partner = near[:, 0].copy()
        for d in range(len(partner)):
            free = near[d][~taken[near[d]]]
            if len(free):
                partner[d] = free[0]
                taken[free[0]] = True
        out.append(partner)
    return out


def _inverted_maxima(js: JointScan, cfg, max_single_share):
    """``J`` of the sign-inverted data's local maxima from ``background_floor``, those one
    detector makes and a data maximum's filter sidelobes left out."""
    j_inv, best = joint_map(-np.stack([m.z for m in js.maps]), js.coefficients)
    r, s = local_maxima(j_inv, cfg.background_floor, js.window)
    share = joint_shares(js.scans, js.maps, js.rows, js.coefficients, best, r, s, sign=-1.0)
    half = int(round(cfg.sidelobe_window * js.scans[0].geometry.sample_rate))
    nearby = window_max(js.j, r, s, 2, half)
    keep = (share <= max_single_share) & (nearby < cfg.max_opposite_ratio * j_inv[r, s])
    return j_inv[r[keep], s[keep]]


def _slide(js: JointScan, cyclic, partial, slid, partners, cfg, rng, min_shift,
           max_single_share):
    """``cfg.n_slides`` time slides of the scan: each band's bright maxima gated out, the
    first band's detectors slid in its groups and every other band's with their pixel
    partners (:func:`pixel_partners`), the joint statistic's local maxima from the slides'
    floor (appended to ``js.slides``, their live time to ``js.live_s``)."""
    floor = max(cfg.background_floor, cfg.slide_floor)
    searches, gated = [], []
    for s, m, c, p, g in zip(js.scans, js.maps, cyclic, partial, slid):
        weights, _ = s.weights(js.rows)
        snr = s.snr
        if g is not None:
            snr = gated_sources(s.snr, p, c, s.geometry, weights, g, m.scale, js.window, cfg)
        gated.append(BandScan(s.band, snr, s.geometry, s.beam_sigma, s.sigma_amp))
        searches.append(SlideSearch(snr, s.geometry, js.rows, s.beam_sigma, s.sigma_amp,
                                    s.live, js.window, g, p))
    nsamp = js.j.shape[1]
    first = group_offsets(slid[0], len(js.scans[0].sigma_amp), nsamp, min_shift, rng,
                          cfg.n_slides)
    offsets = [first[:, partner] for partner in partners]
    scales, coefficients = None, None
    for k in range(cfg.n_slides):
        these = [o[k] for o in offsets]
        z = [search.full_map(search.term_shifts(o)) for search, o in zip(searches, these)]
        if scales is None:       # a slide's spread and correlation are the scan's slides':
            #                      measured on the first
            scales = [measured_scale(zb) for zb in z]
            maps = [BandMap(zb / sc, sc, search.norm / sc)
                    for zb, sc, search in zip(z, scales, searches)]
            coefficients, js.slide_correlation = map_coefficients(
                [s.band for s in js.scans], maps, js.indices)
        j, best = joint_map(np.stack([zb / sc for zb, sc in zip(z, scales)]), coefficients)
        js.live_s += nsamp / js.scans[0].geometry.sample_rate
        r, s = local_maxima(j, floor, js.window)
        if not len(r):
            continue
        share = joint_shares(gated, maps, js.rows, coefficients, best, r, s, offsets=these)
        js.slides.extend(j[r, s][share <= max_single_share])


def joint_background(scans, cfg: SignificanceConfig, indices=DEFAULT_INDICES,
                     max_single_share=0.5, visit=None) -> Background:
    """The :class:`Background` of the joint statistic over a group's scans (``scans``:
    ``(first, [BandScan, ...])`` per scan, :func:`so_transients.coherent.joint.band_scans`),
    in units of ``J``; ``visit(joint_scan)`` is called with each scan's :class:`JointScan`
    (e.g. for the data's candidates) before its maps are dropped."""
    rng = np.random.default_rng(cfg.seed)
    slides, inverted, live_s, data_live_s = [], [], 0.0, 0.0
    for first, bands in scans:
        js = joint_scan(bands, first, cfg, rng, indices, max_single_share)
        if visit is not None:
            visit(js)
        slides.extend(js.slides)
        inverted.extend(js.inverted)
        live_s += js.live_s
        data_live_s += js.data_live_s
    floor = cfg.background_floor
    return Background(np.asarray(slides, float), live_s / 3600.0,
                      np.asarray(inverted, float), data_live_s / 3600.0,
                      tail_from=cfg.tail_from, floor=floor,
                      slide_floor=max(floor, cfg.slide_floor))


def joint_statistic(js: JointScan, bore_q, timestamps, ra, dec, t_cand, peak_window):
    """The highest ``J`` within one row and ``peak_window`` crossing times of the position
    (ra, dec) seen at ``t_cand`` on the scan's joint map (NaN off the map)."""
    i = int(np.clip(np.searchsorted(timestamps, t_cand), 0, len(timestamps) - 1))
    row, t0, _ = map_cell(js.scans[0].geometry, js.rows, js.first, bore_q, ra, dec, i)
    value = window_max(js.j, [row], [t0], 1, int(round(peak_window * js.window)))[0]
    return float(value) if np.isfinite(value) else np.nan


def joint_significance(snr, dets, names, timestamps, bore_q, xi, eta, scan, sigma_amp,
                       beam_sigma, cands, cfg: SignificanceConfig, indices,
                       max_single_share) -> dict:
    """``coherent_snr`` (J near each candidate), ``far``, ``far_slides``, ``far_inverted``
    (per wafer-band-hour: the joint background's rate per hour of the wafer over its
    ``len(names)`` bands, so that ``max_far`` means what it means for one band) and
    ``pass_far`` of joint candidates (``cands``: ``ra``, ``dec``, ``t_median``, ``scan``),
    and the background's ``live_hours``. ``dets``: per band of ``names``, its live
    detectors (rows of ``snr``); ``xi``, ``eta``, ``sigma_amp`` per detector of the group;
    ``beam_sigma`` per band."""
    n = len(cands["scan"])
    stat = np.full(n, np.nan)
    cand_scan = np.asarray(cands["scan"])

    def visit(js):
        for c in np.flatnonzero(cand_scan == scan[js.first]):
            stat[c] = joint_statistic(js, bore_q, timestamps, cands["ra"][c], cands["dec"][c],
                                      cands["t_median"][c], cfg.peak_window)

    scans = band_scans(names, [snr] * len(names), dets, [xi[d] for d in dets],
                       [eta[d] for d in dets], [sigma_amp[d] for d in dets], beam_sigma,
                       timestamps, bore_q, scan)
    background = joint_background(scans, cfg, indices, max_single_share, visit)
    out = {k: v / len(names) for k, v in background.far(stat).items()}
    out["coherent_snr"] = stat
    out["pass_far"] = np.ones(n, bool) if cfg.max_far is None else ~(out["far"] > cfg.max_far)
    return dict(**out, live_hours=background.slide_hours)


def significance_with_joint(snr, timestamps, bore_q, xi, eta, scan, sigma_amp, live,
                            beam_sigma, bands, cands, cfg: SignificanceConfig, vetoes,
                            stacking=None, indices=DEFAULT_INDICES):
    """:func:`so_transients.significance.far.significance_by_band` of a group's candidates,
    its joint-band ones (``joint_id`` >= 0, from ``transient_find``'s ``joint_bands``) ranked
    among the joint statistic's background (:func:`joint_significance`; ``indices``: the
    spectral indices the search maximised over) instead: ``(columns, live_hours,
    z_scale)``."""
    n = len(cands["scan"])
    joint = np.asarray(cands.get("joint_id", np.full(n, -1))) >= 0
    if not joint.any():
        return significance_by_band(snr, timestamps, bore_q, xi, eta, scan, sigma_amp, live,
                                    beam_sigma, bands, cands, cfg, vetoes, stacking)
    out = {k: np.full(n, BY_NAME[k].fill, BY_NAME[k].dtype) for k in COLUMNS}
    live_hours, scale = np.nan, np.nan
    if not joint.all():
        single = {k: np.asarray(v)[~joint] for k, v in cands.items()}
        part, live_hours, scale = significance_by_band(
            snr, timestamps, bore_q, xi, eta, scan, sigma_amp, live, beam_sigma, bands,
            single, cfg, vetoes, stacking)
        for key in COLUMNS:
            out[key][~joint] = part[key]
    names = joint_names(np.asarray(cands["bandpass"])[joint])
    dets = [np.flatnonzero((np.asarray(bands) == b) & np.asarray(live, bool)) for b in names]
    sub = {k: np.asarray(cands[k])[joint] for k in ("scan", "t_median")}
    sub["ra"] = np.asarray(cands["cluster_ra"])[joint]
    sub["dec"] = np.asarray(cands["cluster_dec"])[joint]
    res = joint_significance(snr, dets, names, timestamps, bore_q, xi, eta, scan, sigma_amp,
                             [float(np.median(np.asarray(beam_sigma)[d])) for d in dets], sub,
                             cfg, indices, vetoes.max_single_share)
    # (no chi-squared test of J: coherent_chi2 NaN, coherent_consistent True)
    for key in ("coherent_snr", "far", "far_slides", "far_inverted", "pass_far"):
        out[key][joint] = res[key]
    if not np.isfinite(live_hours):
        live_hours = res["live_hours"]
    return out, float(live_hours), float(scale)


#: The columns ``transient_significance`` fills.
COLUMNS = ("coherent_snr", "coherent_chi2", "coherent_consistent", "far", "far_slides",
           "far_inverted", "pass_far")


def joint_names(bands) -> tuple:
    """The dichroic pair (:data:`so_transients.common.bands.FLAVOR_BANDS`, in its order)
    the joint candidates' bands ``bands`` belong to."""
    present = set(np.asarray(bands).astype(str))
    for pair in FLAVOR_BANDS.values():
        if present <= set(pair):
            return pair
    raise ValueError(f"joint candidates of bands {sorted(present)}: not one dichroic wafer's")
