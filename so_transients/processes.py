"""sotodlib preprocess processes for the transient search: thin wrappers around the core.

Four steps, registered with sotodlib's ``Pipeline`` when ``so_transients`` is imported, to be
listed after the standard steps of a site preprocess config (see
``configs/preprocess_transients.yaml``):

``transient_filter`` -> ``transient_find`` -> ``transient_cuts`` -> ``transient_fit``

They read only standard SO AxisManager fields: ``signal``, ``timestamps``, ``boresight``
(az, el, roll), ``focal_plane`` (xi, eta, gamma), ``det_info`` (the bandpass field named in
the config), ``flags`` and ``obs_info``. Catalogues are saved on the detector axis (see
:mod:`so_transients.catalog`) so that loading a whole observation concatenates every group's
candidates; :mod:`so_transients.results` turns them into tables.
"""
from __future__ import annotations

import logging
import warnings

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from sotodlib import core
from sotodlib.preprocess import Pipeline, _Preprocess
from sotodlib.tod_ops import flags as tod_flags

from . import catalog, pointing
from .bands import ARCMIN, HARDWARE_BAND_KEY, fwhm_to_sigma, fwhm_to_sigma_fwhm, get_band
from .cuts import CutsConfig, apply_cuts, read_catalog
from .find import FindConfig, cap_candidates, find_candidates, scan_segments
from .fit import FitConfig, Track, fit_candidate, null_scatter
from .matched_filter import FilterConfig, filter_kernels, fit_error_inflation, matched_filter

log = logging.getLogger(__name__)
DEFAULT_FWHM_ARCMIN = {b: get_band(b).fwhm / ARCMIN for b in HARDWARE_BAND_KEY}
LAG_AXIS = "transient_lag"
CAND_AXIS = "transient_cand"
HIT_AXIS = "transient_hit"
PSD_BIN_AXIS = "transient_psd_bin"
PSD_EDGE_AXIS = "transient_psd_edge"


# ----------------------------------------------------------------------------- helpers

class describe:
    """'obs_id (wafer, band)' of ``aman`` for error messages; worked out only when shown."""

    def __init__(self, aman):
        self.aman = aman

    def __str__(self):
        aman = self.aman
        obs_id = aman.obs_info.obs_id if "obs_info" in aman else "unknown observation"
        parts = []
        if "det_info" in aman:
            for key in ("wafer_slot", "bandpass"):
                if key in aman.det_info._fields:
                    parts.append(",".join(sorted(set(map(str, aman.det_info[key])))))
        return f"{obs_id} ({', '.join(parts) or 'all detectors'})"


def require(aman, step, *paths):
    """Raise a ValueError naming the observation, group and missing fields."""
    missing = []
    for path in paths:
        node = aman
        for part in path.split("."):
            if not isinstance(node, core.AxisManager) or part not in node._fields:
                missing.append(path)
                break
            node = node[part]
    if missing:
        raise ValueError(f"{step}: {describe(aman)} lacks {', '.join(missing)}")


def check_timestamps(aman, step):
    """Timestamps must increase with a regular step (the filter works in Fourier space)."""
    t = np.asarray(aman.timestamps)
    dt = np.diff(t)
    if len(t) < 2 or not np.all(np.isfinite(t)):
        raise ValueError(f"{step}: {describe(aman)} has too few or non-finite timestamps")
    if np.any(dt <= 0):
        raise ValueError(f"{step}: {describe(aman)} timestamps are not strictly increasing "
                         f"({np.sum(dt <= 0)} steps <= 0)")
    step_med = np.median(dt)
    if dt.max() > 1.5 * step_med:
        raise ValueError(f"{step}: {describe(aman)} timestamps have gaps (largest step "
                         f"{dt.max():.3f} s, nominal {step_med:.4f} s); fill or split the data")
    return 1.0 / step_med


def bandpasses(aman, field):
    """Band name of every detector, from the det_info field ``field`` (dotted paths allowed)."""
    node = aman.det_info
    for part in field.split("."):
        if part not in node._fields:
            raise ValueError(f"{describe(aman)}: det_info has no field {field!r}")
        node = node[part]
    return np.asarray(node).astype(str)


def fwhm_table(cfg):
    """Beam FWHM per band (arcmin): the nominal ones updated by the config's
    ``beam_fwhm_arcmin``, which is taken out of ``cfg``."""
    return {**DEFAULT_FWHM_ARCMIN, **cfg.pop("beam_fwhm_arcmin", {})}


def beam_fwhm(bands, table_arcmin, where):
    unknown = sorted(set(bands) - set(table_arcmin))
    if unknown:
        raise ValueError(f"{where}: no beam FWHM configured for bandpass {unknown}; "
                         f"add it to beam_fwhm_arcmin")
    return np.array([table_arcmin[b] for b in bands]) * ARCMIN


def sample_speed(aman):
    """On-sky speed of the boresight at every sample (rad/s), from az and el."""
    t = np.asarray(aman.timestamps)
    daz = np.gradient(np.unwrap(np.asarray(aman.boresight.az)), t)
    return np.abs(daz) * np.cos(np.asarray(aman.boresight.el))


def scan_speed(aman):
    """Median on-sky speed of the boresight (rad/s) while it scans."""
    speed = sample_speed(aman)
    moving = speed[speed > 0.5 * np.percentile(speed, 90)] if len(speed) else speed
    if not len(moving) or np.median(moving) <= 0:
        raise ValueError(f"{describe(aman)}: the boresight does not scan")
    return float(np.median(moving))


def boresight_mask(flag):
    """Boolean (samps,) mask of a boresight flag: Ranges, RangesMatrix or array (for
    per-detector flags, the first detector's, since they are the same for all)."""
    mask = np.asarray(flag.mask() if hasattr(flag, "mask") else flag, bool)
    return mask[0] if mask.ndim == 2 else mask


BORE_Q = "transient_bore_q"


def boresight_q(aman):
    """Celestial boresight quaternion of every sample, (nsamps, 4), computed once per aman.

    This is one quaternion per sample (25 MB for an hour at 220 Hz), not per detector; it is
    kept in ``aman.transient_bore_q`` (not saved) for the later steps.
    """
    if BORE_Q not in aman._fields:
        roll = aman.boresight.roll if "roll" in aman.boresight._fields else None
        q = pointing.boresight_quats(aman.timestamps, aman.boresight.az, aman.boresight.el, roll)
        aman.wrap(BORE_Q, q, [(0, "samps")])
    return np.asarray(aman[BORE_Q])


def sample_radec(aman, dets, samps):
    """RA/Dec of chosen (detector, sample) pairs only."""
    return pointing.radec_of_samples(boresight_q(aman), aman.focal_plane.xi,
                                     aman.focal_plane.eta, dets, samps)


def drift_velocity(aman, ra, dec, times, half_span=0.05):
    """Velocity (rad/s) of sky positions across the focal plane at the given times, (n, 2)."""
    q = boresight_q(aman)
    t = np.asarray(aman.timestamps)
    out = np.zeros((len(ra), 2))
    for k in range(len(ra)):
        i0, i1 = np.clip(np.searchsorted(t, [times[k] - half_span, times[k] + half_span]),
                         0, len(t) - 1)
        i1 = max(i1, min(i0 + 1, len(t) - 1))
        xi, eta = pointing.source_in_focal_plane(q[[i0, i1]], ra[k], dec[k])
        out[k] = np.array([xi[1] - xi[0], eta[1] - eta[0]]) / max(t[i1] - t[i0], 1e-9)
    return out


def amplitude(aman, dets=slice(None), lo=None, hi=None):
    """Amplitude timestream (signal units) of detectors ``dets``, samples ``lo:hi``: the S/N
    of ``transient_filter`` times each detector's ``sigma_amp``."""
    sigma = np.asarray(aman.transient_filter.sigma_amp, np.float32)[dets]
    return np.asarray(aman.transient_snr[dets, lo:hi]) * sigma[:, None]


def detector_pitch(xi, eta):
    """Median distance between neighbouring detector positions (radians)."""
    pos = np.unique(np.round(np.c_[xi, eta], 12), axis=0)
    if len(pos) < 2:
        return float(np.radians(1.5 / 60))
    dist, _ = cKDTree(pos).query(pos, k=2)
    return float(np.median(dist[:, 1]))


def _dict_to_aman(columns, axis_name, n):
    """An AxisManager holding 1-d ``columns`` (each of length ``n``) on a new IndexAxis.

    Equivalent to wrapping the columns one by one, in one step: each ``wrap`` merges, and a
    merge restricts every field already present, so a catalogue of k columns would cost k^2
    field restrictions (a third of a campaign's search time). The columns are assigned exactly
    as ``AxisManager.wrap`` fills the helper it then merges.
    """
    out = core.AxisManager(core.IndexAxis(axis_name, n))
    for name, values in columns.items():
        values = np.asarray(values)
        if values.ndim != 1 or len(values) != n:
            raise ValueError(f"column {name!r} has shape {values.shape}, expected ({n},)")
        out._fields[name] = values
        out._assignments[name] = [axis_name]
    return out


def _set_columns(sub, columns, axis_name):
    """Add (or replace) ``columns`` on axis ``axis_name`` of ``sub`` in one merge (a wrap per
    column would restrict every field of ``sub`` once per column)."""
    for name in [k for k in columns if k in sub._fields]:
        sub.move(name, None)
    sub.merge(_dict_to_aman(columns, axis_name, sub[axis_name].count),
              restrict_in_place=True)


def _per_det(aman, columns):
    out = core.AxisManager(aman.dets)
    for name, values in columns.items():
        out.wrap(name, np.asarray(values), [(0, "dets")])
    return out


def _table_from_aman(sub, axis):
    return {k: np.asarray(sub[k]) for k in sub._fields if sub._assignments[k] == [axis]}


def _catalog_step_config(step):
    """Calc config of a catalogue step minus the keys every such step shares."""
    cfg = dict(step.calc_cfgs) if isinstance(step.calc_cfgs, dict) else {}
    step.slots = int(cfg.pop("catalog_slots", 4))
    step.bandpass_field = cfg.pop("bandpass_field", "bandpass")
    return cfg


def _save_catalog(proc_aman, aman, name, columns, slots):
    """Store per-candidate ``columns`` in ``proc_aman[name]``, on each candidate's peak detector."""
    peak = np.asarray(aman.transient_candidates.peak_det).astype(int)
    proc_aman.wrap(name, catalog.pack(proc_aman, columns, peak, slots))


def _register(cls):
    """Register with sotodlib's Pipeline once (re-imports in workers are harmless)."""
    if Pipeline.PIPELINE.get(cls.name) is None:
        _Preprocess.register(cls)
    return cls


# ----------------------------------------------------------------------------- the steps

@_register
class TransientFilter(_Preprocess):
    """Matched-filter every detector for point-source crossings (paper eq. 2).

    ``process()`` computes, per detector, the S/N timestream ``aman.transient_snr`` (unit
    variance, verified by measurement; zero where nothing may be detected), plus
    ``aman.transient_filter``: per-detector ``noise_level``, ``fknee``, ``sigma_amp``,
    ``snr_scale``, ``dead``, ``sigma_t``, ``beam_sigma``, ``fit_inflation``, the filter's
    response kernel (``lag``, ``response``) used by ``transient_fit``, and its noise weighting
    (``psd_bins``, ``psd_edges``, ``snr_factor``, ``nfft``, ``order``) from which
    :meth:`so_transients.injection.NoiseModel.from_aman` filters injected signals. The amplitude timestream
    (signal units, mJy for point-source-calibrated data) is ``transient_snr * sigma_amp``;
    :func:`amplitude` computes it for any block of detectors and samples, so the full array
    never needs to be held. It runs again when the archive is loaded, so these are always
    available. The template width is the beam sigma over the scan speed
    measured from the boresight. Samples flagged in the ``aman.flags`` fields listed in
    ``mask_flags`` (and non-finite ones) are ignored and can never be detected; do not list
    glitch flags there, since bright transients are flagged as glitches.

    Saved to the archive (``calc``/``save``): ``proc_aman.transient_filter`` with the
    per-detector fields above (not the kernel).

    Example config block::

      - name: transient_filter
        process:
          bandpass_field: bandpass        # det_info field holding f090, f150, ...
          beam_fwhm_arcmin: {f090: 2.2, f150: 1.4, f220: 1.0, f280: 0.9}
          highpass: 1.23                  # Hz, or "fit" for a per-detector knee
          order: 4
          white_band: [10, 30]            # Hz
          edge_buffer: 5.0                # s without detections at each end
          mask_buffer: 0.2                # s around masked samples
          mask_flags: []                  # aman.flags fields to ignore (not glitches!)
          workers: 1                      # threads filtering chunks of detectors
          chunk_dets: 16                  # detectors per chunk (kept in cache)
        calc: true
        save: true
    """

    name = "transient_filter"

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        cfg = dict(self.process_cfgs or {})
        self.bandpass_field = cfg.pop("bandpass_field", "bandpass")
        self.fwhm_table = fwhm_table(cfg)
        self.mask_flags = list(cfg.pop("mask_flags", []))
        highpass = cfg.pop("highpass", 1.23)
        cfg["highpass"] = None if highpass == "fit" else float(highpass)
        if "white_band" in cfg:
            cfg["white_band"] = tuple(cfg["white_band"])
        self.filter_cfg = FilterConfig(**cfg)

    def _mask(self, aman):
        if not self.mask_flags:
            return None
        mask = np.zeros((aman.dets.count, aman.samps.count), bool)
        for name in self.mask_flags:
            require(aman, self.name, f"flags.{name}")
            flag = aman.flags[name]
            mask |= flag.mask() if hasattr(flag, "mask") else np.asarray(flag, bool)
        return mask

    def process(self, aman, proc_aman, sim=False, data_aman=None):
        require(aman, self.name, "signal", "timestamps", "boresight.az", "boresight.el",
                "det_info")
        fs = check_timestamps(aman, self.name)
        bands = bandpasses(aman, self.bandpass_field)
        beam_sigma = fwhm_to_sigma(beam_fwhm(bands, self.fwhm_table, describe(aman)))
        sigma_t = beam_sigma / scan_speed(aman) if aman.dets.count else beam_sigma
        res = matched_filter(aman.signal, fs, sigma_t, self.filter_cfg, mask=self._mask(aman))
        for name in ("transient_snr", "transient_filter"):
            if name in aman._fields:
                aman.move(name, None)
        aman.wrap("transient_snr", res.snr, [(0, "dets"), (1, "samps")])
        aman.wrap("transient_filter", self._summary(aman, res, fs, sigma_t, beam_sigma))
        return aman, proc_aman

    def _summary(self, aman, res, fs, sigma_t, beam_sigma):
        lags, response, inflation = self._kernels(res, fs, sigma_t)
        out = _per_det(aman, dict(noise_level=res.noise_level, fknee=res.fknee,
                                  sigma_amp=res.sigma_amp, snr_scale=res.snr_scale,
                                  dead=res.dead, sigma_t=sigma_t, beam_sigma=beam_sigma,
                                  fit_inflation=np.full(aman.dets.count, inflation)))
        out.add_axis(core.IndexAxis(LAG_AXIS, len(lags)))
        out.wrap("lag", lags, [(0, LAG_AXIS)])
        out.wrap("response", response, [(0, LAG_AXIS)])
        if res.psd_bins is not None and len(res.psd_bins):   # the noise model (injection)
            out.add_axis(core.IndexAxis(PSD_EDGE_AXIS, len(res.psd_edges)))
            out.add_axis(core.IndexAxis(PSD_BIN_AXIS, res.psd_bins.shape[1]))
            out.wrap("psd_edges", np.asarray(res.psd_edges), [(0, PSD_EDGE_AXIS)])
            out.wrap("psd_bins", np.asarray(res.psd_bins), [(0, "dets"), (1, PSD_BIN_AXIS)])
            out.wrap("snr_factor", np.asarray(res.snr_factor), [(0, "dets")])
            out.wrap("nfft", int(res.nfft))
            out.wrap("order", int(self.filter_cfg.order))
        return out

    def _kernels(self, res, fs, sigma_t):
        if res.median_psd is None:
            lags = np.zeros(1)
            return lags, np.ones(1), 1.0
        live = ~res.dead
        lags, response, acf = filter_kernels(res.nfft, fs, float(np.median(sigma_t[live])),
                                             float(np.median(res.fknee[live])), res.median_psd,
                                             self.filter_cfg.order)
        return lags, response, fit_error_inflation(response, acf)

    def calc_and_save(self, aman, proc_aman):
        require(aman, self.name, "transient_filter")
        self.save(proc_aman, aman.transient_filter)
        return aman, proc_aman

    def save(self, proc_aman, summary):
        if not self.save_cfgs:
            return
        keep = _per_det(summary, {k: summary[k] for k in summary._fields
                                  if summary._assignments[k] == ["dets"]})
        proc_aman.wrap(self.name, keep)


@_register
class TransientFind(_Preprocess):
    """Find candidate source crossings: S/N >= 3 samples clustered on the sky per scan.

    Needs ``transient_filter`` before it. Scans are split at turnarounds from
    ``aman.flags.turnarounds`` (sotodlib's ``flag_turnarounds`` step) when present, otherwise
    computed with ``tod_ops.flags.get_turnaround_flags``. RA/Dec is computed only for the
    selected samples (so3g quaternions). Samples where the scan speed differs from the
    template's by more than ``speed_tolerance`` (the ends of turnarounds) are left out too,
    and so are ``turnaround_buffer`` seconds on either side of them, where the high-pass filter
    still rings from the turnaround.
    DBSCAN clusters them per scan and band with
    ``eps = sigma_FWHM = FWHM / (2 sqrt(ln 2))`` unless ``eps_arcmin`` is given; clusters of more
    than 10 samples on at least ``min_dets`` detectors become candidates (at most
    ``max_candidates`` per group, with a warning). Clusters on fewer detectors are almost all
    noise (thousands per hour) and could never pass ``transient_cuts``' detector-count cut, so
    they are not kept; set ``min_dets: 1`` to keep every cluster, as the paper's Table 1 counts.

    In ``aman`` (for the next steps): ``transient_candidates`` (axis ``transient_cand``) and
    ``transient_hits`` (axis ``transient_hit``: candidate, detector, sample, S/N, RA, Dec of
    every clustered sample). Saved to the archive: ``proc_aman.transient_candidates``, a
    catalogue on the detector axis (``so_transients.catalog``) with ``cand_id``, ``bandpass``,
    ``scan``, ``direction``, ``ra``, ``dec`` (rad), ``t_median``, ``t_start``, ``t_stop``,
    ``t_peak`` (ctime), ``snr_max``, ``n_samples``, ``n_dets``.

    Example config block::

      - name: transient_find
        calc:
          snr_threshold: 3.0
          eps_arcmin: null                # null: sigma_FWHM of each band
          dbscan_min_samples: 5
          min_cluster_samples: 11         # clusters of more than 10 samples
          min_dets: 5                     # ... on at least this many detectors
          max_candidates: 2000
          speed_tolerance: 0.1            # leave out samples scanning >10% off nominal speed
          turnaround_buffer: 2.0          # s left out around those samples
          catalog_slots: 4                # catalogue cells per detector in the archive
        save: true
    """

    name = "transient_find"

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        cfg = _catalog_step_config(self)
        self.fwhm_table = fwhm_table(cfg)
        self.speed_tolerance = float(cfg.pop("speed_tolerance", 0.1))
        self.turnaround_buffer = float(cfg.pop("turnaround_buffer", 2.0))
        eps = cfg.pop("eps_arcmin", None)
        self.find_cfg = FindConfig(eps=None if eps is None else eps * ARCMIN, **cfg)

    def _scans(self, aman):
        if "flags" in aman and "turnarounds" in aman.flags._fields:
            ta = aman.flags.turnarounds
        else:
            try:
                with warnings.catch_warnings():     # sotodlib warns on TODs shorter than a scan
                    warnings.simplefilter("ignore", RuntimeWarning)
                    ta, _, _ = tod_flags.get_turnaround_flags(aman, merge=False, merge_lr=False,
                                                              merge_subscans=False)
            except (ValueError, IndexError):   # shorter than one scan: no turnaround to flag
                ta = np.zeros(aman.samps.count, bool)
        in_ta = boresight_mask(ta)
        # the template assumes the nominal scan speed: leave out samples far from it
        in_ta = in_ta | (np.abs(sample_speed(aman) / scan_speed(aman) - 1) > self.speed_tolerance)
        # the high-pass rings for ~1/f_hp after the kink a turnaround leaves in the atmosphere
        n_buf = int(round(self.turnaround_buffer * (aman.samps.count - 1)
                          / (aman.timestamps[-1] - aman.timestamps[0])))
        if n_buf and in_ta.any():
            in_ta = ndimage.maximum_filter1d(in_ta.view(np.uint8), 2 * n_buf + 1).astype(bool)
        return scan_segments(in_ta, np.asarray(aman.boresight.az))

    def calc_and_save(self, aman, proc_aman):
        require(aman, self.name, "transient_snr", "focal_plane.xi", "focal_plane.eta",
                "boresight.az", "boresight.el")
        bands = bandpasses(aman, self.bandpass_field)
        scan, directions = (self._scans(aman) if aman.dets.count
                            else (np.full(aman.samps.count, -1), np.zeros(0, int)))
        cands, hits = {}, {}
        for band in sorted(set(bands)):
            dets = np.flatnonzero(bands == band)
            fwhm = beam_fwhm([band], self.fwhm_table, describe(aman))[0]
            eps = self.find_cfg.eps or fwhm_to_sigma_fwhm(fwhm)
            radec = lambda d, s, dets=dets: sample_radec(aman, dets[d], s)
            c, h = find_candidates(aman.transient_snr, aman.timestamps, scan, directions,
                                   radec, eps, self.find_cfg, rows=dets)
            c["peak_det"], h["det"] = dets[c["peak_det"].astype(int)], dets[h["det"].astype(int)]
            h["cand"] = h["cand"] + len(cands.get("scan", []))
            c["bandpass"] = np.full(len(c["scan"]), band)
            wafers = (np.asarray(aman.det_info.wafer_slot).astype(str)
                      if "wafer_slot" in aman.det_info._fields else np.full(aman.dets.count, ""))
            c["wafer_slot"] = wafers[c["peak_det"]]
            for store, part in ((cands, c), (hits, h)):
                for k, v in part.items():
                    store[k] = np.concatenate([store[k], v]) if k in store else v
        cands, hits = self._limit(aman, cands, hits)
        self._wrap(aman, cands, hits)
        self.save(proc_aman, aman)
        return aman, proc_aman

    def _limit(self, aman, cands, hits):
        cap = min(self.find_cfg.max_candidates, catalog.capacity(aman.dets.count, self.slots))
        if not cands:
            return cands, hits
        return cap_candidates(cands, hits, cap, describe(aman))

    def _wrap(self, aman, cands, hits):
        n = len(cands.get("scan", []))
        if n == 0:
            cands = {k: np.zeros(0) for k in ("scan", "direction", "ra", "dec", "t_median",
                                              "t_start", "t_stop", "t_peak", "snr_max",
                                              "n_samples", "n_dets", "peak_det")}
            cands["bandpass"] = np.zeros(0, "U4")
            cands["wafer_slot"] = np.zeros(0, "U4")
            hits = {k: np.zeros(0) for k in ("cand", "det", "samp", "snr", "ra", "dec")}
        for name in ("transient_candidates", "transient_hits"):
            if name in aman._fields:
                aman.move(name, None)
        aman.wrap("transient_candidates", _dict_to_aman(cands, CAND_AXIS, n))
        aman.wrap("transient_hits", _dict_to_aman(hits, HIT_AXIS, len(hits["cand"])))

    def save(self, proc_aman, aman):
        if not self.save_cfgs:
            return
        cands = _table_from_aman(aman.transient_candidates, CAND_AXIS)
        cands.pop("peak_det")
        _save_catalog(proc_aman, aman, "transient_candidates", cands, self.slots)


@_register
class TransientCuts(_Preprocess):
    """Cut candidates that are not source-like (paper section 4.2).

    Cuts, in order: at least ``min_dets`` detectors; detectors along the scan direction
    (focal-plane aspect ratio >= ``min_aspect_ratio``); hit times consistent with a source
    drifting across the array at the scan speed (rejects readout glitches and cosmic rays that
    hit many detectors at one instant); not within ``mask_radius_arcmin`` (default
    sigma_FWHM) of a source in the ``catalog`` file (ECSV/CSV with ``ra``, ``dec``). Also sets a
    polarization flag when the detectors mostly share one polarization orientation.

    In ``aman.transient_candidates``: ``pass_<cut>``, ``aspect_ratio``, ``time_rms``,
    ``instant_rms``, ``pol_fraction``, ``pol_flag``, ``cut_reason`` (first failed cut, '' if
    none) and ``passed``. Saved to the archive: ``proc_aman.transient_cuts``, the same columns
    as a catalogue on the detector axis, keyed by ``cand_id``.

    Example config block::

      - name: transient_cuts
        calc:
          min_dets: 5
          min_aspect_ratio: 1.5
          time_tolerance: 0.02            # s
          catalog: null                   # known sources, ECSV or CSV with ra, dec
          catalog_unit: deg               # when the file's columns carry no unit
          mask_radius_arcmin: null        # null: sigma_FWHM of the band
          pol_fraction: 0.8
        save: true
    """

    name = "transient_cuts"

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        cfg = _catalog_step_config(self)
        self.fwhm_table = fwhm_table(cfg)
        radius = cfg.pop("mask_radius_arcmin", None)
        self.cuts_cfg = CutsConfig(mask_radius=None if radius is None else radius * ARCMIN, **cfg)
        self.known = (read_catalog(self.cuts_cfg.catalog, self.cuts_cfg.catalog_unit)
                      if self.cuts_cfg.catalog else (np.zeros(0), np.zeros(0)))

    def calc_and_save(self, aman, proc_aman):
        require(aman, self.name, "transient_candidates", "transient_hits", "focal_plane.gamma")
        cands = _table_from_aman(aman.transient_candidates, CAND_AXIS)
        hits = _table_from_aman(aman.transient_hits, HIT_AXIS)
        hits["cand"], hits["det"], hits["samp"] = (hits[k].astype(int) for k in ("cand", "det", "samp"))
        n = len(cands["scan"])
        drift = drift_velocity(aman, cands["ra"], cands["dec"], cands["t_median"]).reshape(n, 2)
        fp = aman.focal_plane
        xi, eta, gamma = (np.asarray(fp[k]) for k in ("xi", "eta", "gamma"))
        result = {}
        for band in np.unique(cands["bandpass"]):
            sel = np.flatnonzero(cands["bandpass"] == band)
            fwhm = beam_fwhm([band], self.fwhm_table, describe(aman))[0]
            radius = self.cuts_cfg.mask_radius or fwhm_to_sigma_fwhm(fwhm)
            sub_hits = {k: v[np.isin(hits["cand"], sel)] for k, v in hits.items()}
            sub_hits["cand"] = np.searchsorted(sel, sub_hits["cand"])
            part = apply_cuts({k: v[sel] for k, v in cands.items()}, sub_hits, xi, eta, gamma,
                              np.asarray(aman.timestamps), drift[sel], detector_pitch(xi, eta),
                              self.cuts_cfg, self.known, radius)
            for k, v in part.items():
                result.setdefault(k, np.zeros(n, dtype=v.dtype if v.dtype.kind != "U" else "U12"))
                result[k][sel] = v
        if n == 0:
            result = apply_cuts(cands, hits, xi, eta, gamma, aman.timestamps, drift, 1.0,
                                self.cuts_cfg)
        _set_columns(aman.transient_candidates, result, CAND_AXIS)
        self.save(proc_aman, aman, result)
        return aman, proc_aman

    def save(self, proc_aman, aman, result):
        if self.save_cfgs:
            _save_catalog(proc_aman, aman, self.name, result, self.slots)


@_register
class TransientFit(_Preprocess):
    """Fit the beam model A0 B(theta - theta_src) + C to each candidate that passed the cuts.

    All samples of the group within ``window`` s of the candidate's median time and within
    ``radius_deg`` of its position, from detectors whose path passes within
    ``cross_scan_sigma`` beam sigmas of it (the others carry no beam signal), are fitted on the
    amplitude timestream with
    a bounded Levenberg-Marquardt fit (see :mod:`so_transients.fit`); a candidate is a detection when
    ``A0 / sigma_A >= min_snr``. Errors are scaled by ``error_scale``, the measured spread of
    the same fit at ``n_null`` random positions away from candidates (residual atmosphere is
    correlated between neighbouring detectors, so the naive covariance is too small), unless
    a fixed ``error_scale`` is configured (injection campaigns fix it from the noise-only data).

    In ``aman.transient_candidates`` and saved to the archive as ``proc_aman.transient_fit``
    (a catalogue on the detector axis keyed by ``cand_id``): ``flux``, ``flux_err`` (signal
    units, mJy), ``ra``, ``dec``, ``ra_err``, ``dec_err`` (rad; ``ra_err`` is along RA on the
    sky), ``offset``, ``offset_err`` (C), ``snr_fit``, ``chi2_red``, ``n_fit_samples``,
    ``n_fit_dets``, ``fit_ok``, ``error_scale`` and ``detected``. Candidates that did not pass
    the cuts keep NaN fit values and ``detected = False``. ``so-transients catalog`` collects
    these into one table.

    ``plot``: one PNG per detection (S/N of the contributing detectors around the event, and
    their positions on the focal plane) under the pipeline's ``plot_dir``.

    Example config block::

      - name: transient_fit
        calc:
          window: 0.5                     # s around the median time
          radius_deg: 1.0
          min_snr: 5.0
          cross_scan_sigma: 6.0           # detectors passing within this many beam sigmas
          n_null: 200                     # random positions measuring the error scale
          seed: 0                         # for the random null positions
          error_scale: null               # fixed scale (null: measured on this group)
        save: true
        plot: true
    """

    name = "transient_fit"

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        cfg = _catalog_step_config(self)
        self.seed = int(cfg.pop("seed", 0))
        scale = cfg.pop("error_scale", None)
        self.fixed_error_scale = None if scale is None else float(scale)
        radius = cfg.pop("radius_deg", 1.0)
        self.fit_cfg = FitConfig(radius=np.radians(radius), **cfg)

    def calc_and_save(self, aman, proc_aman):
        require(aman, self.name, "transient_candidates", "transient_snr", "transient_filter")
        cands = _table_from_aman(aman.transient_candidates, CAND_AXIS)
        n = len(cands["scan"])
        passed = cands.get("passed", np.ones(n, bool)).astype(bool)
        bands = bandpasses(aman, self.bandpass_field)
        # nulls avoid only possible sources (candidates that passed the cuts): avoiding every
        # candidate would leave only the quietest stretches and bias the scale low
        scales = {b: self.fixed_error_scale or self.error_scale(
                      aman, np.flatnonzero(bands == b), cands["t_median"][passed])
                  for b in np.unique(cands["bandpass"][passed])}
        rows = [self._fit_one(aman, cands, c, np.flatnonzero(bands == cands["bandpass"][c]),
                              scales[cands["bandpass"][c]]) if passed[c] else {}
                for c in range(n)]
        fields = FIT_OUTPUT_FIELDS
        result = {k: np.array([r.get(k, False if k == "fit_ok" else np.nan) for r in rows],
                              dtype=bool if k == "fit_ok" else float) for k in fields}
        result["detected"] = result["fit_ok"] & (np.nan_to_num(result["snr_fit"])
                                                 >= self.fit_cfg.min_snr)
        _set_columns(aman.transient_candidates,
                     {(f"fit_{k}" if k in ("ra", "dec") else k): v for k, v in result.items()},
                     CAND_AXIS)
        self.save(proc_aman, aman, result)
        return aman, proc_aman

    def _window(self, aman, t_center):
        t = np.asarray(aman.timestamps)
        return tuple(np.searchsorted(t, [t_center - self.fit_cfg.window,
                                         t_center + self.fit_cfg.window]))

    def _track(self, aman, ra, dec, lo, hi):
        t = np.asarray(aman.timestamps)
        q = boresight_q(aman)[lo:hi]
        xi, eta = pointing.source_in_focal_plane(q, ra, dec)
        velocity = np.array([xi[-1] - xi[0], eta[-1] - eta[0]]) / (t[hi - 1] - t[lo])
        speed = float(np.hypot(*velocity))
        summary = aman.transient_filter
        return q, Track(xi, eta, velocity / speed, speed, 0.0, np.asarray(summary.lag),
                        np.asarray(summary.response))

    def _fit_window(self, aman, ra, dec, lo, hi, dets):
        """The source's track over samples ``lo:hi`` and the live detectors ``dets`` that pass
        within ``radius`` and ``cross_scan_sigma`` beam sigmas of it: ``(q, track, dets)``."""
        summary = aman.transient_filter
        q, track = self._track(aman, ra, dec, lo, hi)
        mid = (hi - lo) // 2
        xi, eta = np.asarray(aman.focal_plane.xi)[dets], np.asarray(aman.focal_plane.eta)[dets]
        near = pointing.angular_distance_xieta(xi, eta, track.xi[mid],
                                               track.eta[mid]) <= self.fit_cfg.radius
        track.sigma = float(np.median(np.asarray(summary.beam_sigma)[dets])) if len(dets) else 1.0
        across = -(xi - track.xi[mid]) * track.along[1] + (eta - track.eta[mid]) * track.along[0]
        return q, track, dets[near & (np.abs(across) <= self.fit_cfg.cross_scan_sigma * track.sigma)]

    @staticmethod
    def _window_data(aman, track, dets, lo, hi):
        """``(track, det_xi, det_eta, amp, sigma_amp)`` of detectors ``dets``, samples ``lo:hi``."""
        return (track, np.asarray(aman.focal_plane.xi)[dets], np.asarray(aman.focal_plane.eta)[dets],
                amplitude(aman, dets, lo, hi), np.asarray(aman.transient_filter.sigma_amp)[dets])

    def _fit_one(self, aman, cands, c, band_dets, error_scale):
        summary = aman.transient_filter
        lo, hi = self._window(aman, cands["t_median"][c])
        if hi - lo < 4:
            return {}
        live = band_dets[~np.asarray(summary.dead)[band_dets]]
        q, track, dets = self._fit_window(aman, cands["ra"][c], cands["dec"][c], lo, hi, live)
        res = fit_candidate(*self._window_data(aman, track, dets, lo, hi),
                            float(np.median(np.asarray(summary.fit_inflation))), error_scale)
        res["error_scale"] = error_scale
        if res["fit_ok"]:
            mid = (hi - lo) // 2
            res.update(self._to_sky(q[mid:mid + 1], track.xi[mid], track.eta[mid], res))
        return res

    @staticmethod
    def _to_sky(q, xi0, eta0, res):
        """RA/Dec and errors of the fitted focal-plane position at the window's centre."""
        step = 1e-5
        xs = xi0 + res["dxi"] + np.array([0.0, step, 0.0])
        es = eta0 + res["deta"] + np.array([0.0, 0.0, step])
        ra, dec = pointing.radec_of_samples(q, xs, es, [0, 1, 2], [0, 0, 0])
        dra = np.angle(np.exp(1j * (ra[1:] - ra[0]))) * np.cos(dec[0]) / step
        ddec = (dec[1:] - dec[0]) / step
        cov = np.diag([res["dxi_err"] ** 2, res["deta_err"] ** 2])
        jac = np.array([dra, ddec])
        cov_sky = jac @ cov @ jac.T
        return dict(ra=float(ra[0]), dec=float(dec[0]), ra_err=float(np.sqrt(cov_sky[0, 0])),
                    dec_err=float(np.sqrt(cov_sky[1, 1])))

    def error_scale(self, aman, band_dets, cand_times):
        """Measured spread of the fitted amplitude at ``n_null`` random positions of detectors
        ``band_dets``, more than 2 s from ``cand_times``."""
        summary = aman.transient_filter
        dets = band_dets[~np.asarray(summary.dead)[band_dets]]
        t = np.asarray(aman.timestamps)
        rng = np.random.default_rng(self.seed)
        n_win = int(round(self.fit_cfg.window * (len(t) - 1) / (t[-1] - t[0])))
        lo_ok, hi_ok = n_win + 1, len(t) - n_win - 1
        if not len(dets) or hi_ok <= lo_ok:
            return 1.0
        centers = rng.integers(lo_ok, hi_ok, size=4 * self.fit_cfg.n_null)
        far = np.min(np.abs(t[centers][:, None] - np.asarray(cand_times)[None, :]), axis=1,
                     initial=np.inf) > 2.0
        centers = centers[far][: self.fit_cfg.n_null]
        picks = rng.choice(dets, size=len(centers))
        ra, dec = sample_radec(aman, picks, centers)
        windows = []
        for k, s in enumerate(centers):
            lo, hi = s - n_win, s + n_win + 1
            _, track, near = self._fit_window(aman, ra[k], dec[k], lo, hi, dets)
            windows.append(self._window_data(aman, track, near, lo, hi))
        return null_scatter(windows, float(np.median(np.asarray(summary.fit_inflation))))

    def save(self, proc_aman, aman, result):
        if self.save_cfgs:
            renamed = {(f"fit_{k}" if k in ("ra", "dec") else k): v for k, v in result.items()}
            _save_catalog(proc_aman, aman, self.name, renamed, self.slots)

    def plot(self, aman, proc_aman, filename):
        if not self.plot_cfgs:
            return
        from .plots import plot_detection

        cands = aman.transient_candidates
        for c in np.flatnonzero(np.asarray(cands.detected, bool)):
            name = filename.replace("{ctime}", f"{str(aman.timestamps[0])[:5]}")
            name = name.replace("{obsid}", aman.obs_info.obs_id if "obs_info" in aman else "obs")
            name = name.replace("{name}", f"{cands.bandpass[c]}_transient_{c}")
            plot_detection(aman, c, name)


FIT_OUTPUT_FIELDS = ("flux", "flux_err", "ra", "dec", "ra_err", "dec_err", "offset",
                     "offset_err", "snr_fit", "chi2_red", "n_fit_samples", "n_fit_dets",
                     "fit_ok", "error_scale")
