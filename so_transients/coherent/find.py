"""The coherent detection mode of ``transient_find``: maxima of the coherent statistic Z.

The paper's search (:mod:`so_transients.detect.find`) uses a detector only where it alone clears
S/N 3. The coherent mode instead adds every detector's filtered S/N along the path a sky
position takes across the wafer, weighted by the beam across the scan and by its noise
(:func:`so_transients.coherent.statistic.coherent_map`): the maximum-likelihood detection statistic of
a source steady during one crossing. For each scan of each band, Z is evaluated on rows of
positions ``row_step`` beam sigmas apart and at every sample, in units of the map's own
measured spread (residual atmosphere correlates detectors, so it is not 1); its local maxima
at least ``coherent_threshold`` become candidates, the strongest of any that lie within two
beam sigmas across and three beam-crossing times along of each other.

Two glitch vetoes (:mod:`so_transients.coherent.vetoes`) remove what is not a source
crossing before the cuts see it: one detector making more than ``max_single_share`` of a
maximum's sum, or detectors crossed at one instant more than ``max_instant_share`` of it.

A candidate's hits (``transient_hits``) are the samples the sum used: each detector within
``hit_reach`` beam sigmas across, at the sample the position crosses it. The cuts and the
beam fit then run unchanged.

With ``stack_window``, the scans' maps are kept and the crossings of each sky position
within that window are stacked (:mod:`so_transients.coherent.sweep_stack`), for flares that stay
bright over several sweeps.

Everything here is on arrays (a group's S/N, boresight quaternions, focal plane); no
AxisManager.
"""
from __future__ import annotations

import logging

import numpy as np

from so_transients.common import candidates, pointing
from so_transients.coherent.statistic import (
    coherent_map, crossing_geometry, measured_scale, row_offsets, row_weights
)
from so_transients.coherent.config import CoherentConfig
from so_transients.coherent.joint import (
    band_map, band_scans, joint_map, joint_maxima, joint_rows, map_coefficients
)
from so_transients.coherent.vetoes import peaks, suppress_neighbours, sum_terms
from so_transients.common.bands import FLAVOR_BANDS
from so_transients.detect.find import CLUSTER_FIELDS, as_arrays, band_part, merge_bands
from so_transients.common.scan_geometry import sample_rate as rate_of
from so_transients.coherent.sweep_stack import ScanMap, sky_position, stack_seeds

log = logging.getLogger(__name__)


def scan_map(snr, geometry, beam_sigma, sigma_amp, live, cfg, with_flux=True):
    """``(rows, z, flux, n, weights)`` of one scan: the rows' cross-scan offsets, Z in units of
    the map's measured spread, the flux estimate (mJy; None without ``with_flux``), each
    row's inverse flux noise (1/mJy, in the same units) and the detectors' weights in each
    row."""
    rows = row_offsets(geometry, beam_sigma, cfg.row_step)
    z, flux = coherent_map(snr, geometry, rows, beam_sigma, sigma_amp, live,
                           with_flux=with_flux)
    scale = measured_scale(z, lags=geometry.lag_samples)
    weights, norm = row_weights(geometry, rows, beam_sigma, sigma_amp, live)
    return rows, z / scale, flux, norm / scale, weights


def hit_terms(snr, first, geometry, rows, weights, row, sample, beam_sigma, cfg):
    """``hit_dets``, ``hit_samples`` and ``hit_snr`` of the map position (``row`` index,
    ``sample`` in ``snr``): the sum's terms within ``hit_reach`` beam sigmas (all of them
    when none is), rows of ``snr`` and group samples."""
    dets, at, _ = sum_terms(snr, weights, geometry.lag_samples, row, sample)
    near = np.abs(geometry.across[dets] - rows[row]) <= cfg.hit_reach * beam_sigma
    near = near if near.any() else np.ones(len(dets), bool)
    return dict(hit_dets=dets[near], hit_samples=first + at[near],
                hit_snr=np.nan_to_num(snr[dets[near], at[near]]))


def scan_candidates(snr, first, geometry, beam_sigma, sigma_amp, live, cfg, keep=None):
    """The maxima of one scan (``snr``: the band's live detectors over the scan's samples,
    the scan starting at group sample ``first``) that no veto removes: a list of dicts with
    the map position (``row`` offset, ``sample`` in the group), ``map_z``, and ``hit_dets``,
    ``hit_samples``, ``hit_snr`` (:func:`hit_terms`). ``keep(rows, z, flux, n, r, s)``, when
    given, receives the map and its maxima from ``cfg.stack_seed`` (sweep stacking)."""
    # the flux map is needed only by sweep stacking
    rows, z, flux, n, weights = scan_map(snr, geometry, beam_sigma, sigma_amp, live, cfg,
                                         with_flux=keep is not None)
    low = cfg.coherent_threshold if keep is None else min(cfg.stack_seed, cfg.coherent_threshold)
    r, s = peaks(snr, geometry, z, weights, beam_sigma, low, cfg.row_step, cfg.vetoes)
    if keep is not None:
        seed = z[r, s] >= cfg.stack_seed
        keep(rows, z, flux, n, r[seed], s[seed])
    found = []
    for row, sample in zip(r, s):
        if z[row, sample] >= cfg.coherent_threshold:
            found.append(dict(row=rows[row], sample=first + sample, map_z=z[row, sample],
                              **hit_terms(snr, first, geometry, rows, weights, row, sample,
                                          beam_sigma, cfg)))
    return found


def band_candidates(snr, dets, timestamps, bore_q, xi, eta, scan, directions, sigma_amp,
                    beam_sigma, sample_rate, cfg: CoherentConfig, min_dets, where=""):
    """``(candidates, hits)`` of one band of a group in coherent mode (columns
    :data:`so_transients.detect.find.CLUSTER_FIELDS`, ``map_z`` and ``n_crossings``; detector
    indices count in ``dets``, the band's live detectors, rows of the group's ``snr``), with
    the sweep stacks of ``cfg.stack_window`` (:mod:`so_transients.coherent.sweep_stack`)."""
    cands, hits = _empty_lists()
    if len(dets) < min_dets:
        log.warning("%s: %d live detectors, fewer than min_dets = %d: too few for a coherent "
                    "search; no candidates", where, len(dets), min_dets)
        return as_arrays(cands, hits)
    live = np.ones(len(dets), bool)
    stacking = StackInputs() if cfg.stack_window else None
    for k in np.unique(scan[scan >= 0]):
        samples = np.flatnonzero(scan == k)
        if len(samples) < 2:
            continue
        geometry = crossing_geometry(timestamps, bore_q, xi, eta, samples, sample_rate)
        block = np.asarray(snr[dets, samples[0]:samples[-1] + 1])
        keep = stacking.keeper(k, samples, geometry, timestamps, bore_q) if stacking else None
        for peak in scan_candidates(block, samples[0], geometry, beam_sigma, sigma_amp, live,
                                    cfg, keep):
            ra, dec = sky_position(geometry, peak["row"], bore_q, peak["sample"])
            _add(cands, hits, peak, k, directions[k], ra, dec, bore_q, xi, eta, timestamps)
    if stacking:
        for s in stack_seeds(stacking.maps, stacking.seeds, bore_q, timestamps, beam_sigma,
                             cfg.row_step, cfg.stack_window, cfg):
            peak, k = _stack_peak(s, stacking, snr, dets, scan, beam_sigma, sigma_amp, live, cfg)
            _add(cands, hits, peak, k, directions[k], s["ra"], s["dec"], bore_q, xi, eta,
                 timestamps, timestamps[[c.sample for c in s["crossings"]]])
    return as_arrays(cands, hits)


def _empty_lists():
    """Candidate columns (as :func:`_add` appends them) and hit columns, empty."""
    return ({k: [] for k in (*CLUSTER_FIELDS, "map_z", "n_crossings",
                             *candidates.JOINT_FIND_COLUMNS)},
            {k: [] for k in candidates.HIT_COLUMNS})


def joint_candidates(snr, dets, names, timestamps, bore_q, xi, eta, scan, directions, sigma_amp,
                     beam_sigma, cfg: CoherentConfig):
    """Per band of ``names`` (both bands of one wafer), ``(candidates, hits)`` of the
    joint-band statistic's maxima (:mod:`so_transients.coherent.joint`): each maximum of J at
    least ``coherent_threshold`` that neither glitch veto removes (``max_single_share``,
    ``max_instant_share``; the chi-squared test is not applied to J), the strongest of its
    neighbours, is one candidate in each band
    whose detectors it reaches (same position and time, that band's hits and ``map_z``;
    ``joint_z``, the best ``spectral_index``, a shared ``joint_id`` and the scan's
    ``band_correlation``). ``dets``: per band, its live detectors
    (rows of ``snr``), ``xi``, ``eta`` (rad), ``sigma_amp`` (mJy) theirs; ``beam_sigma``
    (rad) per band."""
    parts = [_empty_lists() for _ in names]
    joint_id = 0
    scans = band_scans(names, [snr] * len(names), dets, [xi[d] for d in dets],
                       [eta[d] for d in dets], [sigma_amp[d] for d in dets], beam_sigma,
                       timestamps, bore_q, scan)
    for first, bands in scans:
        k = scan[first]
        rows = joint_rows(bands, cfg.row_step)
        maps = [band_map(b, rows) for b in bands]
        coefficients, correlation = map_coefficients(names, maps, cfg.spectral_indices)
        j, best = joint_map(np.stack([m.z for m in maps]), coefficients)
        window = max(b.geometry.crossing_samples(b.beam_sigma) for b in bands)
        r, s = joint_maxima(bands, maps, rows, coefficients, j, best, cfg.coherent_threshold,
                            window, cfg.max_single_share, cfg.max_instant_share)
        keep = suppress_neighbours(j[r, s], r, s, int(np.ceil(2.0 / cfg.row_step)), 3 * window)
        weights = [b.weights(rows)[0] for b in bands]
        for row, sample in zip(r[keep], s[keep]):
            ra, dec = sky_position(bands[0].geometry, rows[row], bore_q, first + sample)
            for (cands, hits), band, m, d, w in zip(parts, bands, maps, dets, weights):
                peak = dict(map_z=m.z[row, sample], joint_z=j[row, sample], joint_id=joint_id,
                            spectral_index=cfg.spectral_indices[best[row, sample]],
                            band_correlation=correlation[0, 1], sample=first + sample,
                            **hit_terms(band.snr, first, band.geometry, rows, w, row,
                                        sample, band.beam_sigma, cfg))
                if not len(peak["hit_dets"]):     # the row reaches none of this band
                    continue
                _add(cands, hits, peak, k, directions[k], ra, dec, bore_q, xi[d], eta[d],
                     timestamps)
            joint_id += 1
    return [as_arrays(c, h) for c, h in parts]


def joint_pair(bands, live, min_dets):
    """The two bands of one dichroic wafer flavour (:data:`so_transients.common.bands.
    FLAVOR_BANDS`) a group holds, each with at least ``min_dets`` live detectors, or None."""
    present = sorted(set(np.asarray(bands)[np.asarray(live, bool)]))
    for pair in FLAVOR_BANDS.values():
        if list(pair) == present and all(
                np.sum((np.asarray(bands) == b) & live) >= min_dets for b in pair):
            return pair
    return None


class StackInputs:
    """The maps and seeds of a band's scans, kept for sweep stacking."""

    def __init__(self):
        self.maps, self.seeds = [], []

    def keeper(self, k, samples, geometry, timestamps, bore_q):
        """The ``keep`` callback of :func:`scan_candidates` for scan ``k``."""
        first = int(samples[0])

        def keep(rows, z, flux, n, r, s):
            self.maps.append(ScanMap(int(k), first, geometry, rows, z.astype(np.float32),
                                     flux.astype(np.float32), n, float(timestamps[first]),
                                     float(timestamps[samples[-1]])))
            for row, sample in zip(r, s):
                ra, dec = sky_position(geometry, rows[row], bore_q, first + sample)
                self.seeds.append((int(k), first + int(sample), ra, dec))
        return keep


def _stack_peak(s, stacking, snr, dets, scan, beam_sigma, sigma_amp, live, cfg):
    """A stack as :func:`_add` takes a peak: its hits are those of its strongest crossing
    (the cuts look at one crossing, as for every candidate); returns ``(peak, scan)``."""
    best = max(s["crossings"], key=lambda c: c.n * c.z)
    m = next(m for m in stacking.maps if m.scan == best.scan)
    samples = np.flatnonzero(scan == best.scan)
    block = np.asarray(snr[dets, samples[0]:samples[-1] + 1])
    weights, _ = row_weights(m.geometry, m.rows, beam_sigma, sigma_amp, live)
    peak = dict(row=m.rows[best.row], sample=best.sample, map_z=s["z"],
                n_crossings=len(s["crossings"]),
                **hit_terms(block, m.first, m.geometry, m.rows, weights, best.row,
                            best.sample - m.first, beam_sigma, cfg))
    return peak, best.scan


def _add(cands, hits, peak, scan, direction, ra, dec, bore_q, xi, eta, t, span=None):
    """Append a peak at (ra, dec) as a candidate; ``span``: the times its crossings pass
    the wafer's centre (a stack's: ``t_start`` and ``t_stop`` cover them)."""
    cid = len(cands["scan"])
    d, s, v = peak["hit_dets"], peak["hit_samples"], peak["hit_snr"]
    best = int(np.argmax(v)) if len(v) else 0
    times = t[s] if len(s) else t[[peak["sample"]]]
    span = times if span is None else np.r_[times, span]
    for key, value in (("scan", scan), ("direction", direction), ("cluster_ra", ra),
                       ("cluster_dec", dec), ("t_median", t[peak["sample"]]),
                       ("t_start", span.min()), ("t_stop", span.max()),
                       ("t_peak", times[best]), ("snr_max", v[best] if len(v) else np.nan),
                       ("n_samples", len(s)), ("n_dets", len(np.unique(d))),
                       ("peak_det", d[best] if len(d) else -1), ("map_z", peak["map_z"]),
                       ("n_crossings", peak.get("n_crossings", 1)),
                       ("joint_z", peak.get("joint_z", np.nan)),
                       ("spectral_index", peak.get("spectral_index", np.nan)),
                       ("joint_id", peak.get("joint_id", -1)),
                       ("band_correlation", peak.get("band_correlation", np.nan))):
        cands[key].append(value)
    hit_ra, hit_dec = pointing.radec_of_samples(bore_q, xi, eta, d, s)
    for key, value in (("det", d), ("samp", s), ("snr", v), ("ra", hit_ra), ("dec", hit_dec)):
        hits[key].extend(value)
    hits["cand"].extend([cid] * len(d))


def coherent_group_candidates(snr, timestamps, bore_q, xi, eta, scan, directions, bands, wafers,
                              live, sigma_amp, beam_sigma, cfg: CoherentConfig, min_dets, cap,
                              where=""):
    """Candidates of a whole group (every band of it) in coherent mode, at most ``cap`` of
    them (highest ``map_z``): ``(candidates, hits)`` with every ``transient_find`` column,
    detector indices counting in the group. ``live``, ``sigma_amp`` (mJy), ``beam_sigma``
    (rad): per detector, from ``transient_filter``; a band with fewer than ``min_dets`` live
    detectors is not searched."""
    sample_rate = rate_of(timestamps, where)
    parts = []
    pair = joint_pair(bands, live, min_dets) if cfg.joint_bands else None
    if cfg.joint_bands and pair is None:
        log.warning("%s: joint_bands needs both bands of one wafer in the group, each with at "
                    "least min_dets = %d live detectors (subobs use: [wafer_slot]); found %s: "
                    "each band is searched alone", where or "group", min_dets,
                    sorted(set(np.asarray(bands)[live])))
    if pair is not None:
        if cfg.stack_window:
            log.warning("%s: joint_bands searches single crossings: stack_window is not "
                        "applied", where or "group")
        dets = [np.flatnonzero((bands == b) & live) for b in pair]
        found = joint_candidates(snr, dets, pair, timestamps, bore_q, xi, eta, scan, directions,
                                 sigma_amp, [float(np.median(beam_sigma[d])) for d in dets],
                                 cfg)
        return merge_bands([band_part(c, h, d, b, wafers)
                            for (c, h), d, b in zip(found, dets, pair)], cap, where)
    for band in sorted(set(bands)):
        dets = np.flatnonzero((bands == band) & live)
        c, h = band_candidates(snr, dets, timestamps, bore_q, xi[dets], eta[dets], scan,
                               directions, sigma_amp[dets], float(np.median(beam_sigma[dets]))
                               if len(dets) else np.nan, sample_rate, cfg, min_dets,
                               f"{where}: band {band}" if where else f"band {band}")
        parts.append(band_part(c, h, dets, band, wafers))
    return merge_bands(parts, cap, where)
