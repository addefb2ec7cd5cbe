"""sotodlib preprocess processes for the transient search: thin wrappers around the core.

Five steps, registered with sotodlib's ``Pipeline`` when ``so_transients`` is imported, to be
listed after the standard steps of a site preprocess config (see
``configs/preprocess_paper.yaml``):

``transient_filter`` -> ``transient_find`` -> ``transient_cuts`` -> ``transient_significance``
-> ``transient_fit``

``transient_significance`` is optional: without it, ``transient_fit`` follows ``transient_cuts``.
Each step reads its config into its dataclass (:mod:`so_transients.common.step_config`) when the
pipeline is built, checks the fields it reads (:mod:`so_transients.preprocess.step_fields`: standard
SO fields only), calls its core (:mod:`~so_transients.detect.matched_filter`,
:mod:`~so_transients.detect.find`, :mod:`~so_transients.detect.cuts`,
:mod:`~so_transients.significance.far`, :mod:`~so_transients.detect.fit`) and stores the result.
Candidates carry the columns of :mod:`so_transients.common.candidates`; they are saved on the
detector axis (:mod:`so_transients.preprocess.slot_storage`) so that loading a whole observation
concatenates every group's candidates, and :mod:`so_transients.site.results` turns them into
tables. Nothing but package registration imports this module.
"""
from __future__ import annotations

import logging
from dataclasses import fields, replace

import numpy as np
from sotodlib import core
from sotodlib.preprocess import Pipeline, _Preprocess

from so_transients.common import candidates, pointing, scan_geometry
from so_transients.preprocess import slot_storage
from so_transients.common.bands import fwhm_to_sigma, sigma_fwhm_by_band
from so_transients.common.candidates import CAND_AXIS, HIT_AXIS
from so_transients.coherent.config import FIND_CONFIGS, CoherentConfig, find_settings, stacking_of
from so_transients.coherent.find import coherent_group_candidates
from so_transients.detect.cuts import CutsConfig, cut_group_candidates
from so_transients.detect.find import SCAN_FIELD, find_group_candidates, group_scans
from so_transients.detect.fit import SPEED_TOLERANCE, FitConfig, FitInputs
from so_transients.detect.fit_candidates import fit_group_candidates
from so_transients.detect import spectral_ops
from so_transients.detect.common_mode import ExcursionConfig, mask_excursions
from so_transients.detect.health import health_warnings, weight_health
from so_transients.detect.jumps import JumpConfig, remove_common_jumps
from so_transients.significance.far import SignificanceConfig, far_is_limit
from so_transients.significance.joint_far import significance_with_joint
from so_transients.coherent.vetoes import Vetoes
from so_transients.coherent.sweep_stack import StackSettings
from so_transients.detect.matched_filter import (
    EXCLUDED, FilterConfig, matched_filter, response_kernels
)
from so_transients.common.step_config import ConfigError, from_yaml
from so_transients.sources.catalog import read_catalogue
from so_transients.preprocess.step_fields import (
    POINTING, POINTING_OPTIONAL, GroupName, StepSpec, require
)
from so_transients.score.model import load_model

log = logging.getLogger(__name__)
LAG_AXIS = "transient_lag"
PSD_BIN_AXIS = "transient_psd_bin"
PSD_EDGE_AXIS = "transient_psd_edge"
SLOTS = "archive_slots"      # scalars in aman.transient_candidates: find's archive slots ...
MIN_DETS = "min_dets"        # ... and detector threshold, for the later steps (and
#                              fit.SPEED_TOLERANCE, the scan-speed tolerance; and the
#                              fields of sweep_stack.StackSettings for transient_significance)
SPECTRAL_INDICES = "spectral_indices"   # ... and the joint-band search's indices (an array)


def _register(cls):
    """Register with sotodlib's Pipeline once (re-imports in workers are harmless)."""
    if Pipeline.PIPELINE.get(cls.name) is None:
        _Preprocess.register(cls)
    return cls


def _per_det(aman, columns):
    out = core.AxisManager(aman.dets)
    for name, values in columns.items():
        out.wrap(name, np.asarray(values), [(0, "dets")])
    return out


def _replace(aman, name, value, axes=None):
    """Wrap ``value`` as ``aman[name]``, replacing a field of that name (a rerun).

    Moving a sub-AxisManager out leaves its axes (e.g. ``transient_hit``) in ``aman``, and
    wrapping the new one would then restrict it to the old length: a rerun with more
    candidates or hits lost the extra ones. Axes no other field uses are dropped first."""
    if name in aman._fields:
        aman.move(name, None)
        used = {a for assigned in aman._assignments.values() for a in assigned if a}
        for axis in [a for a in aman._axes if a not in used and a not in ("dets", "samps")]:
            del aman._axes[axis]
    aman.wrap(name, value, axes)


def _save_candidates(step, proc_aman, aman, columns):
    """Store ``columns`` (with each candidate's ``cand_id``) in ``proc_aman[step.name]``, on
    the detector where each candidate peaked."""
    if not step.save_cfgs:
        return
    cands = aman.transient_candidates
    columns = {"cand_id": np.asarray(cands.cand_id), **columns}
    saved = {k: v for k, v in columns.items() if candidates.BY_NAME[k].saved}
    proc_aman.wrap(step.name, slot_storage.pack(proc_aman, saved, np.asarray(cands.peak_det),
                                                int(cands[SLOTS])))


def _report_searchable(scan, where, warn_below=0.5):
    """Fraction of the group's samples that are searched (not turnaround, nominal speed);
    logged, as a warning below ``warn_below``."""
    fraction = float(np.mean(scan >= 0)) if len(scan) else 0.0
    level = logging.WARNING if fraction < warn_below else logging.INFO
    log.log(level, "%s: %.0f %% of the time is searchable (%d scans); turnarounds, samples "
            "off the nominal speed and the buffers around them are not searched%s", where,
            100 * fraction, int(scan.max()) + 1 if len(scan) else 0,
            " -- a short observation loses most of its scans" if fraction < warn_below else "")
    return fraction


def _check_live(excluded, where, cfg):
    """Log how many detectors the filter cannot use and why (as a warning when more than
    ``cfg.max_excluded`` of them); raise (the group is then recorded as failed) when it can
    use none."""
    n, n_dead = len(excluded), int(np.sum(excluded > 0))
    if n and n_dead == n:
        raise ValueError(f"{where}: no usable detector: all {n} have no finite, non-constant "
                         f"data or a white noise outside {cfg.min_noise_ratio:g}-"
                         f"{cfg.max_noise_ratio:g} x their band's median (NaN samples before "
                         f"a PCA step spread to every detector: cut them first)")
    why = ", ".join(f"{int(np.sum(excluded == code))} {text}" for code, text in EXCLUDED.items()
                    if code and np.any(excluded == code))
    level = logging.WARNING if n_dead > cfg.max_excluded * n else logging.INFO
    log.log(level, "%s: %d of %d detectors not used%s", where, n_dead, n,
            f" ({why})" if why else "")


def _check_weights(sigma_amp, excluded, where):
    """Log the effective number of detectors the group's weights leave (as a warning,
    saying what is out of range, when :func:`so_transients.detect.health.health_warnings`
    finds anything)."""
    health = weight_health(sigma_amp, np.asarray(excluded) == 0)
    problems = health_warnings(health)
    level = logging.WARNING if problems else logging.INFO
    log.log(level, "%s: effective number of detectors %.1f of %d used, largest weight share "
            "%.3g%s", where, health["n_eff"], health["n_used"], health["max_weight_share"],
            f" -- {'; '.join(problems)}: fluxes and positions may be wrong" if problems else "")


# ----------------------------------------------------------------------------- the steps

@_register
class TransientJumps(_Preprocess):
    """Remove readout jumps from ``aman.signal`` itself, before the standard steps that mix
    detectors (``pca_filter``) or differentiate them (time-constant deconvolution).

    A readout jump of a few Jy is, to a PCA, a mode of its own: each jumping detector takes one
    of the modes the atmosphere needed, and the atmosphere left in every detector is noise
    correlated between neighbours that the beam fit adds up into false detections. The jumps
    are found in each detector minus its share of the wafer's common mode, as changes of its
    median level that no crossing can make, so sources are untouched (sotodlib's
    ``fix_jumps`` erases a bright crossing): :func:`so_transients.detect.jumps.remove_common_jumps`.
    Non-finite samples are interpolated over to look for jumps and left non-finite.
    ``aman.transient_n_jumps`` counts the jumps removed per detector (saved with ``save``).

    Config block (after ``detrend``, before ``fourier_filter`` and ``pca_filter``)::

      - name: transient_jumps
        process:
          threshold: 8.0        # times the spread of a detector's level changes
          window: 2.0           # s of median level compared on each side
        save: true
    """

    name = "transient_jumps"
    spec = StepSpec(configs=(JumpConfig,),
                    requires=("signal", "timestamps"))

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        self.cfg = from_yaml(JumpConfig, self.process_cfgs, self.name)

    def process(self, aman, proc_aman, sim=False, data_aman=None):
        where = f"{self.name}: {GroupName(aman)}"
        require(aman, self.name)
        counts = np.zeros(aman.dets.count, int)
        if aman.dets.count and aman.samps.count:
            fs = scan_geometry.sample_rate(aman.timestamps, where)
            signal = aman.signal
            rows = np.flatnonzero(~np.isfinite(signal).all(axis=1))
            bad = ~np.isfinite(signal[rows])
            filled = signal[rows]
            spectral_ops.interpolate_runs(filled, bad)   # an all-NaN row becomes zeros
            signal[rows] = filled
            # constant rows (all-NaN ones included, now zeros) are not in the common mode
            counts = remove_common_jumps(signal, fs, self.cfg, live=np.ptp(signal, axis=1) > 0)
            filled = signal[rows]
            filled[bad] = np.nan
            signal[rows] = filled
            log.info("%s: %d jumps removed from %d of %d detectors", where, counts.sum(),
                     np.count_nonzero(counts), aman.dets.count)
        _replace(aman, "transient_n_jumps", counts, [(0, "dets")])
        return aman, proc_aman

    def calc_and_save(self, aman, proc_aman):
        if self.save_cfgs:
            _replace(proc_aman, self.name, _per_det(aman, {"n_jumps": aman.transient_n_jumps}))
        return aman, proc_aman


@_register
class TransientPcaMask(_Preprocess):
    """Hide sources from the PCA: in the PCA's model signal (``pca_filter``'s ``model_signal``,
    the low-passed copy), each detector's brief excursions beyond its baseline (its share of
    the wafer's common mode plus a running median of the rest) are replaced by the baseline.

    A bright crossing in the model signal can become part of a PCA mode, or bias a detector's
    weight on the modes, and ``pca_filter`` then subtracts part of the source from the signal
    itself. ``aman.signal`` is not touched. ``aman.transient_pca_mask`` holds, per detector,
    the samples replaced (``masked``) and the excursion beyond which a sample is (``limit``, in
    the model signal's units), and the ``buffer`` (s) masked around each:
    :func:`so_transients.detect.common_mode.mask_excursions`.

    Config block (after the low-pass ``fourier_filter``, before ``pca_filter``)::

      - name: transient_pca_mask
        process:
          signal: lpf_signal    # the model signal pca_filter reads
          threshold: 5.0        # times a detector's spread about its baseline
          buffer: 0.2           # s masked around each excursion
    """

    name = "transient_pca_mask"
    spec = StepSpec(configs=(ExcursionConfig,),
                    requires=("timestamps",))

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        self.cfg = from_yaml(ExcursionConfig, self.process_cfgs, self.name)

    def process(self, aman, proc_aman, sim=False, data_aman=None):
        where = f"{self.name}: {GroupName(aman)}"
        require(aman, self.name, [self.cfg.signal])
        counts = np.zeros(aman.dets.count, int)
        limits = np.full(aman.dets.count, np.inf)
        if aman.dets.count and aman.samps.count:
            model = aman[self.cfg.signal]
            fs = scan_geometry.sample_rate(aman.timestamps, where)
            rows = np.flatnonzero(np.isfinite(model).all(axis=1))
            if len(rows) == aman.dets.count:
                counts, limits = mask_excursions(model, fs, self.cfg)
            elif len(rows):
                part = model[rows]
                counts[rows], limits[rows] = mask_excursions(part, fs, self.cfg)
                model[rows] = part
            log.info("%s: %d samples of %d detectors hidden from the PCA", where,
                     counts.sum(), np.count_nonzero(counts))
        mask = core.AxisManager(aman.dets)
        mask.wrap("masked", counts, [(0, "dets")])
        mask.wrap("limit", limits, [(0, "dets")])
        mask.wrap("buffer", float(self.cfg.buffer))
        _replace(aman, self.name, mask)
        return aman, proc_aman


@_register
class TransientFilter(_Preprocess):
    """Matched-filter every detector for point-source crossings (paper eq. 2).

    ``process()`` computes, per detector, the S/N timestream ``aman.transient_snr`` (unit
    variance, verified by measurement; zero where nothing may be detected), plus
    ``aman.transient_filter``: per-detector ``bandpass``, ``noise_level``, ``fknee``,
    ``sigma_amp``, ``snr_scale``, ``dead``, ``sigma_t``, ``beam_sigma``, ``fit_inflation``, the
    filter's response to a crossing (``lag``; ``response`` per detector, from its band's
    median noise) used by ``transient_fit``, and its noise
    weighting (``psd_bins``, ``psd_edges``, ``snr_factor``, ``n_eff``, ``nfft``, ``order``,
    ``bright_bias``) from which
    :meth:`so_transients.campaign.noise_model.NoiseModel.from_aman` filters injected signals. The later
    steps read each detector's band and beam from here: they are configured once, in this
    step. The amplitude timestream (signal units, mJy for point-source-calibrated data) is
    ``transient_snr * sigma_amp``; :func:`so_transients.site.results.amplitude` computes it for any
    block of detectors and samples, so the full array never needs to be held. It runs again
    when the archive is loaded, so these are always available. The template width is the
    beam sigma over the scan speed measured from the boresight. Readout jumps (steps of a
    detector's median level) are removed from the filter's copy of the data first
    (:mod:`so_transients.detect.jumps`; ``jump_threshold``), leaving sources untouched.
    ``excluded`` says why a detector is not used, ``n_jumps`` how many jumps were removed from
    it and ``masked_fraction`` how much of its time is not searched
    (:mod:`so_transients.site.losses` reads them back per group). Samples flagged in the
    ``aman.flags`` fields listed in ``mask_flags`` (and non-finite ones) are ignored and can
    never be detected; do not list glitch flags there, since bright transients are flagged
    as glitches.

    Saved to the archive (``calc``/``save``): ``proc_aman.transient_filter`` with the numeric
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
    spec = StepSpec(configs=(FilterConfig,),
                    requires=("signal", "timestamps", "boresight.az", "boresight.el", "det_info"),
                    optional=("obs_info.obs_id", "flags"))

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        self.cfg = from_yaml(FilterConfig, self.process_cfgs, self.name)

    def _mask(self, aman):
        if not self.cfg.mask_flags:
            return None
        require(aman, self.name, [f"flags.{name}" for name in self.cfg.mask_flags])
        mask = np.zeros((aman.dets.count, aman.samps.count), bool)
        for name in self.cfg.mask_flags:
            flag = aman.flags[name]
            mask |= flag.mask() if hasattr(flag, "mask") else np.asarray(flag, bool)
        return mask

    def _bandpasses(self, aman):
        field = self.cfg.bandpass_field
        node = aman.det_info
        for part in field.split("."):
            if part not in node._fields:
                raise ValueError(f"{self.name}: {GroupName(aman)}: det_info has no field "
                                 f"{field!r} (bandpass_field)")
            node = node[part]
        return np.asarray(node).astype(str)

    def process(self, aman, proc_aman, sim=False, data_aman=None):
        require(aman, self.name)
        where = f"{self.name}: {GroupName(aman)}"
        fs = scan_geometry.sample_rate(aman.timestamps, where)
        bands = self._bandpasses(aman)
        try:
            beam_sigma = fwhm_to_sigma(self.cfg.beam_fwhm(bands))
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        speed = (scan_geometry.scan_speed(aman.timestamps, aman.boresight.az, aman.boresight.el,
                                          str(GroupName(aman))) if aman.dets.count else 1.0)
        sigma_t = beam_sigma / speed
        res = matched_filter(aman.signal, fs, sigma_t, self.cfg, mask=self._mask(aman),
                             groups=bands)
        _check_live(res.excluded, where, self.cfg)
        _check_weights(res.sigma_amp, res.excluded, where)
        _replace(aman, "transient_snr", res.snr, [(0, "dets"), (1, "samps")])
        _replace(aman, "transient_filter", self._summary(aman, res, fs, sigma_t, beam_sigma, bands))
        return aman, proc_aman

    def _summary(self, aman, res, fs, sigma_t, beam_sigma, bands):
        lags, response, inflation = response_kernels(res, fs, sigma_t, bands, self.cfg.order)
        out = _per_det(aman, dict(noise_level=res.noise_level, fknee=res.fknee,
                                  sigma_amp=res.sigma_amp, snr_scale=res.snr_scale,
                                  dead=res.dead, sigma_t=sigma_t, beam_sigma=beam_sigma,
                                  fit_inflation=inflation, bandpass=bands,
                                  excluded=res.excluded, n_jumps=res.n_jumps, n_eff=res.n_eff,
                                  masked_fraction=res.masked_fraction.astype(np.float32)))
        out.add_axis(core.IndexAxis(LAG_AXIS, len(lags)))
        out.wrap("lag", lags, [(0, LAG_AXIS)])
        out.wrap("response", response, [(0, "dets"), (1, LAG_AXIS)])
        if res.psd_bins is not None and len(res.psd_bins):   # the noise model (injection)
            out.add_axis(core.IndexAxis(PSD_EDGE_AXIS, len(res.psd_edges)))
            out.add_axis(core.IndexAxis(PSD_BIN_AXIS, res.psd_bins.shape[1]))
            out.wrap("psd_edges", np.asarray(res.psd_edges), [(0, PSD_EDGE_AXIS)])
            out.wrap("psd_bins", np.asarray(res.psd_bins), [(0, "dets"), (1, PSD_BIN_AXIS)])
            out.wrap("snr_factor", np.asarray(res.snr_factor), [(0, "dets")])
            out.wrap("nfft", int(res.nfft))
            out.wrap("order", int(self.cfg.order))
            out.wrap("bright_bias", np.inf if self.cfg.bright_bias is None
                     else float(self.cfg.bright_bias))
        return out

    def calc_and_save(self, aman, proc_aman):
        require(aman, self.name, ["transient_filter"])
        self.save(proc_aman, aman.transient_filter)
        return aman, proc_aman

    def save(self, proc_aman, summary):
        if not self.save_cfgs:
            return
        keep = _per_det(summary, {k: summary[k] for k in summary._fields
                                  if summary._assignments[k] == ["dets"]
                                  and np.asarray(summary[k]).dtype.kind in "biuf"})
        proc_aman.wrap(self.name, keep)


@_register
class TransientFind(_Preprocess):
    """Find candidate source crossings: S/N >= 3 samples clustered on the sky per scan.

    Needs ``transient_filter`` before it (each detector's band and beam come from there).
    Every sample scanning at the template's speed (within ``speed_tolerance``, measured from
    ``aman.boresight``) is searched, up to the first and last sample of each
    constant-velocity stretch; the turnarounds, where the speed falls towards zero, split the
    scans (``aman.flags.turnarounds`` is not used: its buffers reach into the scans).
    ``turnaround_buffer`` seconds around the turnarounds can be left out as well (0 by
    default). RA/Dec is computed only for the selected samples (so3g quaternions). DBSCAN
    clusters them per scan and band with
    ``eps = sigma_FWHM = FWHM / (2 sqrt(ln 2))`` unless ``eps_arcmin`` is given; clusters of more
    than 10 samples on at least ``min_dets`` detectors become candidates (at most
    ``max_candidates`` per group, with a warning). Clusters on fewer detectors are almost all
    noise (thousands per hour) and could never pass ``transient_cuts``' detector-count cut, so
    they are not kept; set ``min_dets: 1`` to keep every cluster, as the paper's Table 1 counts.

    In ``aman`` (for the next steps): ``transient_candidates`` (axis ``transient_cand``, the
    ``transient_find`` columns of :mod:`so_transients.common.candidates`) and ``transient_hits``
    (axis ``transient_hit``: candidate, detector, sample, S/N, RA, Dec of every clustered
    sample). Saved to the archive: ``proc_aman.transient_find``, the same columns on the
    detector axis (:mod:`so_transients.preprocess.slot_storage`, ``archive_slots`` cells per detector),
    and ``searchable_fraction`` (per detector, the same for the group): the fraction of the
    time that was searched, logged as a warning below one half (short observations).

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
          turnaround_buffer: 0.0          # s left out around those samples
          archive_slots: 4                # candidate cells per detector in the archive
          mode: paper                     # or coherent (below)
          coherent_threshold: 4.5         # coherent: maxima of Z at least this ...
          row_step: 0.8                   # ... on rows this many beam sigmas apart
          max_single_share: 0.5           # veto: one detector makes more of the sum
          max_instant_share: 0.5          # veto: detectors crossed at one instant make more
          chi2_bins: 6                    # veto: chi-squared test over 6 detector groups
          chi2_tail: 0.001                # ... failing this share of noise maxima
          chi2_mismatch: 0.15             # ... allowing this model error (share of Z)
          hit_reach: 2.0                  # hits: detectors within this many beam sigmas
          stack_window: null              # s: stack crossings this long (null: no stacking)
          stack_seed: 3.0                 # stacks start from single-crossing maxima this high
          stack_max_share: 0.7            # ... and one crossing makes at most this of the sum
          joint_bands: false              # both bands of a wafer together (below)
          spectral_indices: [-1, 0, 1, 2, 3]   # ... J maximised over these
        save: true

    ``mode: coherent`` replaces the S/N >= 3 clustering by the maxima of the coherent
    statistic Z (every detector's S/N along a sky position's path across the wafer, weighted
    by the beam and its noise; :mod:`so_transients.coherent.find`), in units of each scan's
    measured spread; ``map_z`` holds it. The DBSCAN settings and ``min_cluster_samples`` are
    then unused; ``min_dets`` is the fewest live detectors a band needs. The cuts and the fit
    run unchanged on its candidates. With ``stack_window`` (seconds) it also stacks the
    crossings of a sky position within that window (sweep stacking, for flares lasting
    several sweeps; :mod:`so_transients.coherent.sweep_stack`): a stack that reaches
    ``coherent_threshold`` and beats each of its crossings alone becomes a candidate with
    ``n_crossings`` > 1, whose hits are its strongest crossing's and whose ``t_start`` /
    ``t_stop`` span its crossings; ``transient_fit`` fits it with the position held on each
    crossing and combines the fluxes, and ``transient_significance`` gives it a ``far``
    from stacks of the scans' maps slid against each other and of the sign-inverted maps.
    The glitch vetoes (the chi-squared test asks
    whether the detectors' S/N are in the proportions a source crossing gives them;
    :mod:`so_transients.coherent.vetoes`) and the stacking settings are kept in
    ``aman.transient_candidates`` for ``transient_significance``, which selects its
    background with them.

    ``joint_bands: true`` (coherent mode) searches a group holding both bands of a dichroic
    wafer (``subobs: use: [wafer_slot]``) with the joint-band statistic J
    (:mod:`so_transients.coherent.joint`): both bands' maps on shared positions, combined
    with the weights a spectral index implies and their measured correlation, maximised over
    ``spectral_indices``. Each maximum of J is one candidate per band (``joint_z``,
    ``spectral_index``, a shared ``joint_id``); ``transient_significance`` ranks J among its
    own background, ``transient_fit`` combines the two bands' fits (``snr_joint``). A group
    without both bands is searched band by band, with a warning. Off by default:
    docs/results/joint_bands.md has what it gains.
    """

    name = "transient_find"
    spec = StepSpec(configs=FIND_CONFIGS,
                    requires=("transient_snr", "transient_filter.bandpass",
                              "transient_filter.beam_sigma") + POINTING,
                    optional=("det_info.wafer_slot",) + POINTING_OPTIONAL)

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        self.cfg, self.coherent = find_settings(self.calc_cfgs, self.name)

    def _scans(self, aman):
        if not aman.dets.count:
            return np.full(aman.samps.count, -1), np.zeros(0, int)
        return group_scans(aman.timestamps, aman.boresight.az, aman.boresight.el, self.cfg,
                           str(GroupName(aman)))

    def calc_and_save(self, aman, proc_aman):
        require(aman, self.name)
        bands = np.asarray(aman.transient_filter.bandpass).astype(str)
        wafers = (np.asarray(aman.det_info.wafer_slot).astype(str)
                  if "det_info" in aman and "wafer_slot" in aman.det_info._fields
                  else np.full(aman.dets.count, ""))
        scale = sigma_fwhm_by_band(aman.transient_filter.beam_sigma, bands)
        eps = {b: self.cfg.eps or e for b, e in scale.items()}
        scan, directions = self._scans(aman)
        q = pointing.boresight_q(aman)
        xi, eta = aman.focal_plane.xi, aman.focal_plane.eta
        radec = lambda d, s: pointing.radec_of_samples(q, xi, eta, d, s)
        cap = min(self.cfg.max_candidates, aman.dets.count * self.cfg.archive_slots)
        if self.cfg.mode == "coherent":
            f = aman.transient_filter
            cands, hits = coherent_group_candidates(
                aman.transient_snr, np.asarray(aman.timestamps), q, np.asarray(xi),
                np.asarray(eta), scan, directions, bands, wafers, ~np.asarray(f.dead, bool),
                np.asarray(f.sigma_amp), np.asarray(f.beam_sigma), self.coherent,
                self.cfg.min_dets, cap,
                str(GroupName(aman)))
        else:
            cands, hits = find_group_candidates(aman.transient_snr, aman.timestamps, scan,
                                                directions, radec, bands, wafers, eps,
                                                self.cfg, cap, str(GroupName(aman)))
        table = candidates.to_aman(cands, CAND_AXIS, len(cands["scan"]))
        table.wrap(SLOTS, int(self.cfg.archive_slots))
        table.wrap(MIN_DETS, int(self.cfg.min_dets))
        table.wrap(SPEED_TOLERANCE, float(self.cfg.speed_tolerance))
        stacking = stacking_of(self.cfg, self.coherent)
        for name in (f.name for f in fields(StackSettings)):
            table.wrap(name, np.nan if stacking is None else getattr(stacking, name))
        for name in (f.name for f in fields(Vetoes)):
            table.wrap(name, float(getattr(self.coherent, name)))
        table.wrap(SPECTRAL_INDICES, np.asarray(self.coherent.spectral_indices, float))
        _replace(aman, "transient_candidates", table)
        _replace(aman, "transient_hits", candidates.to_aman(hits, HIT_AXIS, len(hits["cand"])))
        _replace(aman, SCAN_FIELD, scan.astype(np.int32), [(0, "samps")])
        _save_candidates(self, proc_aman, aman, cands)
        searchable = _report_searchable(scan, str(GroupName(aman)))
        if self.save_cfgs:     # per detector, so that groups concatenate along dets
            proc_aman[self.name].wrap("searchable_fraction",
                                      np.full(aman.dets.count, searchable), [(0, "dets")])
        return aman, proc_aman


@_register
class TransientCuts(_Preprocess):
    """Cut candidates that are not source-like (paper section 4.2).

    Cuts, in order: at least ``min_dets`` detectors (``transient_find``'s setting, read from
    what it stored); detectors along the scan direction
    (focal-plane aspect ratio >= ``min_aspect_ratio``); hit times consistent with a source
    drifting across the array at the scan speed (rejects readout glitches and cosmic rays that
    hit many detectors at one instant); no signal of opposite sign more than
    ``max_opposite_ratio`` times stronger on the same detectors within ``sidelobe_window`` s
    (the filter's sidelobes of a strong negative signal); not within ``mask_radius_arcmin`` (default
    sigma_FWHM, from the beam ``transient_filter`` stored) of a source in the
    ``known_sources`` list (an ECSV/CSV file with ``ra``, ``dec``, or SO's source catalogue
    by URL: ``socat:///path/socat.db``, ``sqlite:///...``, ``postgresql://...``; read when
    the pipeline is built: a missing, empty or malformed file is an error naming it, a list
    without rows a warning that nothing is masked). Also sets a polarization flag when the
    detectors mostly share one polarization orientation.

    In ``aman.transient_candidates``: the ``transient_cuts`` columns of
    :mod:`so_transients.common.candidates` (``pass_<cut>``, ``aspect_ratio``, ``time_rms``,
    ``instant_rms``, ``pol_fraction``, ``pol_flag``, ``cut_reason``: first failed cut, '' if
    none, ``passed``). Saved to the archive: ``proc_aman.transient_cuts``, the same columns on
    the detector axis, keyed by ``cand_id``.

    Example config block::

      - name: transient_cuts
        calc:
          min_aspect_ratio: 1.5
          time_tolerance: 0.02            # s
          known_sources: null             # ECSV/CSV with ra, dec, or a socat URL
          known_sources_unit: deg         # when the file's columns carry no unit
          mask_radius_arcmin: null        # null: sigma_FWHM of the band
          pol_fraction: 0.8
          sidelobe_window: 1.0            # s searched for a signal of opposite sign ...
          max_opposite_ratio: 2.0         # ... this many times stronger: a filter sidelobe
        save: true
    """

    name = "transient_cuts"
    spec = StepSpec(configs=(CutsConfig,),
                    requires=("transient_candidates", "transient_hits", "transient_snr",
                              "focal_plane.gamma", "transient_filter.beam_sigma") + POINTING,
                    optional=POINTING_OPTIONAL)

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        self.cfg = from_yaml(CutsConfig, self.calc_cfgs, self.name)
        # read and checked here, when the pipeline is built: a bad file stops every group
        # before its data are loaded, with one line naming the step, the key and the file
        self.known = (np.zeros(0), np.zeros(0))
        if self.cfg.known_sources is not None:
            known = read_catalogue(self.cfg.known_sources, self.cfg.known_sources_unit,
                                   f"{self.name}: known_sources",
                                   f"{self.name}: known_sources_unit")
            self.known = (known.ra, known.dec)

    def calc_and_save(self, aman, proc_aman):
        require(aman, self.name)
        cands = candidates.from_aman(aman.transient_candidates, CAND_AXIS)
        hits = candidates.from_aman(aman.transient_hits, HIT_AXIS)
        bands = np.asarray(aman.transient_filter.bandpass).astype(str)
        scale = sigma_fwhm_by_band(aman.transient_filter.beam_sigma, bands)
        radius = {b: self.cfg.mask_radius or r for b, r in scale.items()}
        drift = scan_geometry.drift_velocity(aman.timestamps, pointing.boresight_q(aman),
                                             cands["cluster_ra"], cands["cluster_dec"],
                                             cands["t_median"])
        fp = aman.focal_plane
        xi, eta, gamma = (np.asarray(fp[k]) for k in ("xi", "eta", "gamma"))
        result = cut_group_candidates(cands, hits, xi, eta, gamma, np.asarray(aman.timestamps),
                                      drift, scan_geometry.detector_pitch(xi, eta), self.cfg,
                                      self.known, radius, aman.transient_snr,
                                      int(aman.transient_candidates[MIN_DETS]))
        candidates.add_to_aman(aman.transient_candidates, result, CAND_AXIS)
        _save_candidates(self, proc_aman, aman, result)
        return aman, proc_aman


@_register
class TransientSignificance(_Preprocess):
    """A false-alarm rate for every candidate, from time slides and the sign-inverted data.

    Optional, between ``transient_cuts`` and ``transient_fit``. For each scan and band, the
    coherent statistic Z (the maximum-likelihood S/N of a steady source over one wafer
    crossing: every detector's filtered S/N at the time the position crosses it, weighted by
    the beam across the scan and its noise) is computed at every position the wafer sees, on
    the data and on ``n_slides`` time slides (each detector's S/N shifted cyclically within
    the scan by a random offset of at least ``min_slide_s``, alike for the detectors of one
    of ``slide_groups`` random groups, so that the slides share the groups' partial maps;
    the data's own maxima from ``slide_gate`` are gated out of what is slid first; see
    :mod:`so_transients.significance.slide_groups`; ``slide_groups: 0``: every detector its own
    offset). Each candidate gets the
    highest Z near its position and crossing time, each map in units of its own measured
    spread, and two false-alarm rates per hour of this wafer-band: ``far_slides``, the slides'
    maxima at least as high (live time: ``n_slides`` x the time searched; the slides break
    the residual atmosphere's correlation between detectors, so it runs low), and
    ``far_inverted``, the maxima of the sign-inverted data's map (every correlation kept, no
    source; the data's own live time), counted, and beyond ``tail_from`` also by a
    Gaussian-like model of their tail (:mod:`so_transients.significance.tail_model`) so that rates below
    one per live time are resolved. ``far`` is the higher of the two. With ``max_far`` (per
    wafer-band-hour), a candidate above it is not ``detected`` by ``transient_fit``. See
    :mod:`so_transients.significance.far` and :mod:`so_transients.coherent.statistic`.

    Both backgrounds' maxima are put to ``transient_find``'s chi-squared test (the settings
    it stored with its candidates): a candidate whose own maximum passes it is ranked among
    the background maxima that pass it, one that fails among all of them.

    Joint-band candidates (``transient_find``'s ``joint_bands``, ``joint_id`` >= 0) are
    ranked among the joint statistic's own time slides and sign-inverted data
    (:mod:`so_transients.significance.joint_far`), their ``far`` per hour of the wafer
    divided by its two bands, so that ``max_far`` means the same; J has no chi-squared test.

    A sweep stack (``n_crossings`` > 1) is ranked among stacks, seeded and selected as
    ``transient_find`` selects the data's: ``far_slides`` from ``n_slides`` stack slides
    (each scan's map moved along the scan by its own random offset, the seed's held;
    :mod:`so_transients.significance.stack_slides`), ``far_inverted`` from the sign-inverted maps'.

    Reads the scans ``transient_find`` searched (``aman.transient_scan``). In
    ``aman.transient_candidates``: ``coherent_snr``, ``coherent_chi2``,
    ``coherent_consistent``, ``far``, ``far_slides``, ``far_inverted`` (1/h),
    ``far_is_limit`` (``far`` is the slides' resolution, a bound), ``pass_far``;
    the group's background live time and Z scale as ``significance_live_hours`` and
    ``significance_z_scale``. Saved to the archive as ``proc_aman.transient_significance``
    (on the detector axis, keyed by ``cand_id``).

    Example config block::

      - name: transient_significance
        calc:
          n_slides: 100                   # background live time: 100 x the data's (0: none;
          #                                 null: as many as max_far needs, at least 100)
          min_slide_s: 2.0                # every detector shifted at least this far
          slide_groups: 4                 # detectors slid alike in 4 random groups (0: each
          #                                 its own offset, about 4x the cost)
          slide_gate: 6.0                 # data maxima from this Z gated out of the slides
          row_step: 0.8                   # beam sigmas between rows of positions
          background_floor: 3.0           # background maxima counted from this Z
          slide_floor: 4.5                # slides' maxima from this Z (below: inverted data)
          peak_window: 2.0                # crossing times searched around a candidate
          max_single_share: 0.5           # background maxima one detector makes: left out
          max_far: null                   # per wafer-band-hour; null: report only
          seed: 0
          tail_from: 3.5                  # inverted maxima's tail modelled from this Z
          sidelobe_window: 1.0            # s: inverted maxima this close to a data maximum
          max_opposite_ratio: 2.0         # ... this many times higher: its sidelobe, left out
        save: true
    """

    name = "transient_significance"
    spec = StepSpec(configs=(SignificanceConfig,),
                    requires=("transient_candidates", "transient_snr", "transient_scan",
                              "transient_filter.sigma_amp", "transient_filter.dead",
                              "transient_filter.beam_sigma",
                              "transient_filter.bandpass") + POINTING,
                    optional=POINTING_OPTIONAL)

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        self.cfg = from_yaml(SignificanceConfig, self.calc_cfgs, self.name)

    def calc_and_save(self, aman, proc_aman):
        require(aman, self.name)
        cands = aman.transient_candidates
        rows = candidates.from_aman(cands, CAND_AXIS)
        f = aman.transient_filter
        bands = np.asarray(f.bandpass).astype(str)
        scan, t = np.asarray(aman[SCAN_FIELD]), np.asarray(aman.timestamps)
        searched_hours = np.count_nonzero(scan >= 0) * np.median(np.diff(t)) / 3600.0
        cfg = replace(self.cfg, n_slides=self.cfg.slides_for(searched_hours))
        result, live, scale = significance_with_joint(
            aman.transient_snr, t, pointing.boresight_q(aman),
            np.asarray(aman.focal_plane.xi), np.asarray(aman.focal_plane.eta), scan,
            np.asarray(f.sigma_amp), ~np.asarray(f.dead, bool), np.asarray(f.beam_sigma),
            bands, rows, cfg, _vetoes(cands), _stacking(cands), _spectral_indices(cands))
        if not np.isfinite(live):
            log.warning("%s: %s: no band with live detectors: far not computed (NaN), "
                        "candidates pass", self.name, GroupName(aman))
        elif cfg.n_slides and not live > 0:
            log.warning("%s: %s: no constant-speed scan with live detectors long enough for "
                        "time slides: far from the sign-inverted data alone", self.name,
                        GroupName(aman))
        elif cfg.n_slides and cfg.max_far is not None and live * cfg.max_far < 0.5:
            # a statistic above every slide maximum gets far_slides = 0.5 / live
            log.warning("%s: %s: %.2f h of slides cannot resolve max_far = %g per hour (every "
                        "single-crossing candidate has far >= %.3g): raise n_slides",
                        self.name, GroupName(aman), live, self.cfg.max_far, 0.5 / live)
        result["far_is_limit"] = far_is_limit(result["far"], result["far_slides"], live)
        candidates.add_to_aman(cands, result, CAND_AXIS)
        _replace(cands, "significance_live_hours", live)
        _replace(cands, "significance_z_scale", scale)
        _save_candidates(self, proc_aman, aman, result)
        return aman, proc_aman


def _stored(cands, cls):
    """``transient_find``'s settings named by ``cls``'s fields, as stored with its
    candidates (a setting an older archive lacks: ``CoherentConfig``'s default)."""
    default = CoherentConfig()
    return {f.name: float(cands[f.name]) if f.name in cands._fields
            else getattr(default, f.name) for f in fields(cls)}


def _stacking(cands) -> StackSettings | None:
    """``transient_find``'s sweep stacking, or None."""
    stored = _stored(cands, StackSettings)
    window = stored["stack_window"]
    return StackSettings(**stored) if window is not None and np.isfinite(window) else None


def _spectral_indices(cands) -> tuple:
    """The spectral indices ``transient_find``'s joint-band statistic was maximised over."""
    if SPECTRAL_INDICES in cands._fields:
        return tuple(np.asarray(cands[SPECTRAL_INDICES], float))
    return CoherentConfig().spectral_indices


def _vetoes(cands) -> Vetoes:
    """``transient_find``'s glitch vetoes."""
    stored = _stored(cands, Vetoes)
    return Vetoes(**{**stored, "chi2_bins": int(stored["chi2_bins"])})


@_register
class TransientFit(_Preprocess):
    """Fit the beam model A0 B(theta - theta_src) + C to each candidate that passed the cuts.

    All samples of the group within ``window`` s of the candidate's median time and within
    ``radius_deg`` of its position, from detectors whose path passes within
    ``cross_scan_sigma`` beam sigmas of it (the others carry no beam signal), are fitted on the
    amplitude timestream with a bounded Levenberg-Marquardt fit (see :mod:`so_transients.detect.fit`);
    a candidate is a detection when ``A0 / sigma_A >= min_snr`` and it is not a moving source
    (its group's significant fits at that place drift from scan to scan faster than
    ``min_motion_arcmin_per_min``: flagged ``moving``, see :mod:`so_transients.detect.motion`)
    nor a repeat of a detection of the same crossing (fits of one scan and band within a beam
    FWHM: ``duplicate_of`` names the one kept, see
    :func:`so_transients.detect.fit_candidates.crossing_duplicates`), and the fits of two
    halves of its detectors agree within ``max_split_sigma`` errors (``split_sigma``,
    ``pass_split``: a fit pulled off the source by a few detectors whose data or weights
    are wrong does not, see :func:`so_transients.detect.fit.split_sigma`). Errors are scaled by
    ``error_scale``, the measured spread of the same fit at ``n_null`` random positions clear
    of the candidates (residual atmosphere is correlated between neighbouring detectors, so
    the naive covariance is too small), measured in each scan direction and applied to each
    candidate by the direction of its sweep (the wind makes the residual atmosphere differ
    between sweeps of increasing and decreasing azimuth, see
    :mod:`so_transients.detect.error_scale`), unless a fixed ``error_scale`` is configured
    (one number, or ``[increasing, decreasing]``; injection campaigns fix it from the
    noise-only data). With ``local_window``, a fit significant at that scale is refitted with
    the scale measured at ``n_null_local`` positions of its sweep direction within
    ``local_window`` seconds of it when that is larger (the noise is not stationary).

    In ``aman.transient_candidates`` and saved to the archive as ``proc_aman.transient_fit``
    (on the detector axis, keyed by ``cand_id``): the ``transient_fit`` columns of
    :mod:`so_transients.common.candidates` (``flux``, ``flux_err`` in mJy, ``ra``, ``dec``,
    ``ra_err``, ``dec_err`` in rad, ``snr_fit``, ``detected``, ...). Candidates that did not
    pass the cuts keep NaN fit values, their cluster position and ``detected = False``.
    ``so-transients catalog`` collects these into one table.

    With a ``score_model`` (a model file, or ``shipped``: the package's, trained by
    ``so-transients study train-score``, see :mod:`so_transients.score`), each fitted
    candidate gets ``real_score``, the probability that it is a real source rather than an
    artefact, from the shape of its cluster and fit; with ``min_real_score`` a candidate
    scored below it is not detected (``pass_score`` False).

    ``plot``: one PNG per detection under the pipeline's ``plot_dir``, as
    ``<plot_dir>/<ctime[:5]>/<obs_id>/transient_fit_<wafer>_<band>_cand<cand_id>.png`` (named
    by the step, not by its place in ``process_pipe``): the contributing detectors' amplitude
    with the fitted beam model over them, flux with error, fitted S/N, RA/Dec and UTC time,
    the ``transient_find`` mode that found it with its ``map_z`` and ``far``, and the
    detectors' place on the focal plane (:func:`so_transients.preprocess.plots.plot_detection`).

    Example config block::

      - name: transient_fit
        calc:
          window: 0.5                     # s around the median time
          radius_deg: 1.0
          min_snr: 5.0
          cross_scan_sigma: 6.0           # detectors passing within this many beam sigmas
          n_null: 200                     # random positions measuring the error scale (each direction)
          local_window: null              # s: also measured this near each significant fit
          n_null_local: 400               # random positions of that local measurement
          seed: 0                         # for the random null positions
          error_scale: null               # fixed scale, or [increasing az, decreasing az] (null: measured)
          max_motion_arcmin_per_min: 5.0  # detections linked across scans up to this rate
          min_motion_arcmin_per_min: 0.1  # linked ones moving faster: a moving source
          motion_floor_arcsec: 10.0       # position error floor of the motion test
          max_peak_ratio: null            # 3: not detected when snr_max > 3 x snr_fit
          max_split_sigma: 5.0            # not detected when two halves' fits disagree more
          split_floor_arcsec: 10.0        # their position error floor
          split_floor_flux: 0.1           # their flux error floor (of the flux)
          score_model: null               # real-or-artefact model: a file, or shipped
          min_real_score: null            # not detected when real_score is below this
        save: true
        plot: true
    """

    name = "transient_fit"
    spec = StepSpec(configs=(FitConfig,),
                    requires=("transient_candidates", "transient_snr", "transient_filter.bandpass",
                              "transient_filter.sigma_amp", "transient_filter.dead",
                              "transient_filter.beam_sigma", "transient_filter.fit_inflation",
                              "transient_filter.lag", "transient_filter.response") + POINTING,
                    optional=("transient_hits",) + POINTING_OPTIONAL)

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        self.cfg = from_yaml(FitConfig, self.calc_cfgs, self.name)
        self.model = None
        if self.cfg.score_model is not None:
            try:
                self.model = load_model(self.cfg.score_model)
            except (OSError, ValueError) as exc:
                raise ConfigError(f"{self.name}: score_model: {exc}") from None

    def _score(self, cands):
        """``real_score`` and ``pass_score`` of the candidates (columns with the fit's)."""
        values = self.model.score(cands)
        cut = self.cfg.min_real_score
        return values, (values >= cut) if cut is not None else np.ones(len(values), bool)

    def calc_and_save(self, aman, proc_aman):
        require(aman, self.name)
        cands = candidates.from_aman(aman.transient_candidates, CAND_AXIS)
        bands = np.asarray(aman.transient_filter.bandpass).astype(str)
        result = fit_group_candidates(FitInputs.from_aman(aman), cands, bands, self.cfg,
                                      score=self._score if self.model else None)
        candidates.add_to_aman(aman.transient_candidates, result, CAND_AXIS)
        _save_candidates(self, proc_aman, aman, result)
        return aman, proc_aman

    def plot(self, aman, proc_aman, filename):
        if not self.plot_cfgs:
            return
        from so_transients.preprocess.plots import detection_filename, plot_detection

        cands = aman.transient_candidates
        for c in np.flatnonzero(np.asarray(cands.detected, bool)):
            plot_detection(aman, c, detection_filename(filename, aman, c, self.name))
