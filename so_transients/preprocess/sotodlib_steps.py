"""sotodlib's heaviest standard steps, as the production config runs them, with the same keys
and results but a chunk's memory instead of whole-signal copies.

For one hour of an f090 wafer-band (2.7 GB of float32 signal) sotodlib's ``pca_filter``,
``glitches`` and ``fourier_filter`` each hold two or three full copies of the signal at once
(float64 covariances, FFT buffers, the filter's response for every detector, masks): they
make the site pipeline's peak memory (docs/results/performance.md). Here:

- ``transient_pca_filter``: ``pca_filter`` with the covariance, modes and subtraction in
  blocks of samples (:mod:`so_transients.detect.pca`);
- ``transient_fourier_filter``: ``fourier_filter`` (the same filters and keys) run on chunks
  of ``chunk_dets`` detectors, each filtered as sotodlib filters it;
- ``transient_glitches``: ``glitches`` (``get_glitch_flags``, its flags and significances
  saved and selected on as sotodlib does) run on chunks of detectors.

The two per-detector steps call sotodlib's own functions on a light AxisManager of each
chunk (its detectors' signal and the fields the functions read), so they give sotodlib's
result for every detector to float32 rounding (FFTW may round a row differently in batches
of another size or with other threads; on the tested wafers, with 32 detectors a chunk and
one thread, to the bit).
"""
from __future__ import annotations

import inspect
import logging

import numpy as np
import scipy.sparse
from so3g.proj import RangesMatrix
from sotodlib import core, tod_ops
from sotodlib.preprocess.processes import FourierFilter, GlitchDetection, _Preprocess

from so_transients.detect.pca import PcaConfig, pca_filter
from so_transients.common.step_config import ChunkConfig, ConfigError, from_yaml
from so_transients.preprocess.processes import _register, _replace
from so_transients.preprocess.step_fields import GroupName, StepSpec, has_field, require

log = logging.getLogger(__name__)

#: sotodlib's step of each chunked equivalent here (the same keys and results)
SOTODLIB_STEP = {"transient_pca_filter": "pca_filter",
                 "transient_fourier_filter": "fourier_filter",
                 "transient_glitches": "glitches"}


def sotodlib_name(step_name):
    """The sotodlib step a config's step name runs: itself, or the one a chunked equivalent
    stands for."""
    return SOTODLIB_STEP.get(step_name, step_name)


def chunk_setting(step, cfg):
    """``chunk_dets`` popped from the config block ``cfg`` of ``step`` (a ConfigError names
    the step and the key unless it is a positive integer)."""
    value = cfg.pop("chunk_dets", ChunkConfig.chunk_dets)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{step}: chunk_dets must be a positive integer, got {value!r}")
    return value


def chunks(ndet, size):
    """Slices of ``size`` detectors covering ``ndet``."""
    return [slice(s, min(s + size, ndet)) for s in range(0, ndet, size)]


def chunk_aman(aman, sl, fields):
    """An AxisManager of detectors ``sl`` of ``aman`` holding ``timestamps`` and the dotted
    ``fields`` (those with a detector axis restricted to the chunk, the others shared)."""
    dets = core.LabelAxis(aman.dets.name, aman.dets.vals[sl])
    sub = core.AxisManager(dets, aman.samps)
    sub.wrap("timestamps", aman.timestamps, [(0, aman.samps.name)])
    for path in fields:
        parts = path.split(".")
        src, dst = aman, sub
        for part in parts[:-1]:
            src = src[part]
            if part not in dst._fields:
                dst.wrap(part, core.AxisManager(dets, aman.samps))
            dst = dst[part]
        name = parts[-1]
        value = src[name]
        axes = src._assignments.get(name, ())
        if isinstance(value, core.AxisManager):
            if aman.dets.name in value._axes:
                value = value.restrict(aman.dets.name, dets.vals, in_place=False)
            dst.wrap(name, value)
        elif axes and axes[0] == aman.dets.name:
            dst.wrap(name, value[sl], [(0, aman.dets.name)] + [
                (i, a) for i, a in enumerate(axes) if i and a is not None])
        else:
            dst.wrap(name, value, [(i, a) for i, a in enumerate(axes) if a is not None])
    return sub


@_register
class TransientPcaFilter(_Preprocess):
    """sotodlib's ``pca_filter`` step (the same keys, modes and result) without its full
    float64 copies of the signal: the covariance, modes and subtraction are computed in blocks
    of samples (:func:`so_transients.detect.pca.pca_filter`). For one hour of an f090
    wafer-band this lowers the site pipeline's peak memory by the 5.4 GB ``np.cov`` makes and
    halves the step's time (docs/results/performance.md). Detectors whose model signal is not
    finite everywhere are left out and not cleaned, with a warning naming the group
    (sotodlib's step spreads one NaN to every detector). ``aman.transient_pca_filter`` keeps
    what was subtracted: ``weights`` (dets, pca_modes), each detector's weight on the modes
    (zero where ``left_out``), from which an injection recovery models the step
    (:mod:`so_transients.campaign.pca_response`).

    Config block (in place of ``pca_filter``)::

      - name: transient_pca_filter
        model_signal: lpf_signal   # optional: the modes' signal (default: signal itself)
        signal: signal
        process:
          n_modes: 10
    """

    name = "transient_pca_filter"
    spec = StepSpec(configs=(PcaConfig,),
                    requires=())

    def __init__(self, step_cfgs):
        self.signal = step_cfgs.get("signal", "signal")
        self.model_signal = step_cfgs.get("model_signal", None)
        super().__init__(step_cfgs)
        self.cfg = from_yaml(PcaConfig, self.process_cfgs, self.name)

    def process(self, aman, proc_aman, sim=False, data_aman=None):
        where = f"{self.name}: {GroupName(aman)}"
        require(aman, self.name, [self.signal] + ([self.model_signal] if self.model_signal
                                                  else []))
        signal = aman[self.signal]
        model = aman[self.model_signal] if self.model_signal else signal
        try:
            result = pca_filter(signal, model, self.cfg.n_modes, self.cfg.block)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        modes = core.AxisManager(aman.dets, core.IndexAxis("pca_modes", self.cfg.n_modes))
        modes.wrap("weights", result.weights, [(0, "dets"), (1, "pca_modes")])
        modes.wrap("left_out", result.left_out, [(0, "dets")])
        _replace(aman, self.name, modes)
        left_out = result.left_out
        if left_out.any():
            log.warning("%s: %d of %d detectors have a model signal (%s) that is not finite "
                        "everywhere: left out of the PCA and not cleaned", where,
                        left_out.sum(), aman.dets.count, self.model_signal or self.signal)
        return aman, proc_aman


def _field_paths(aman, filter_name, params):
    """The fields of ``aman`` sotodlib's filter ``filter_name`` may read with ``params``: each
    of its arguments given or defaulting to a string that names a field (``timeconst:
    det_cal.tau_eff``, ``tau_name='timeconst'``), or left None where a field of the argument's
    own name stands in (``timeconst``, ``iir_params``)."""
    params = params or {}
    out = []
    for name, arg in inspect.signature(getattr(tod_ops.filters, filter_name)).parameters.items():
        value = params.get(name, arg.default)
        path = name if value is None else value
        if isinstance(path, str) and has_field(aman, path):
            out.append(path)
    return out


@_register
class TransientFourierFilter(FourierFilter):
    """sotodlib's ``fourier_filter`` step (the same keys and filters) run on chunks of
    ``chunk_dets`` detectors (``process:`` key, :class:`ChunkConfig`), each chunk with
    sotodlib's ``tod_ops.filters.fourier_filter`` and FFT buffers reused from chunk to chunk:
    the same filtered signal (to float32 rounding), without the step's whole-signal FFT
    buffers and per-detector filter responses (for the time-constant deconvolution of one
    hour of an f090 wafer-band, sotodlib's step peaks at 3.2 times the signal). Filters read
    the fields their arguments name (``timeconst: det_cal.tau_eff``, or a field of the
    argument's own name, ``iir_params``) for the chunk's detectors; ``noise_fit_array`` is
    not supported (use ``fourier_filter``), nor a signal stored as (samps, dets). With
    ``wrap_name`` equal to ``signal_name`` the signal is filtered in place (sotodlib's step
    wraps a new array): anything sharing the array sees the filtered signal.

    Config block (in place of ``fourier_filter``)::

      - name: transient_fourier_filter
        signal_name: signal
        wrap_name: lpf_signal      # a low-passed copy (signal itself: filtered in place)
        process: {filt_function: low_pass_butter4, filter_params: {fc: 3.0}, chunk_dets: 32}
    """

    name = "transient_fourier_filter"
    spec = StepSpec(configs=(ChunkConfig,),
                    requires=("timestamps",))

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        cfg = dict(self.process_cfgs or {})
        self.chunk_dets = chunk_setting(self.name, cfg)
        if cfg.get("noise_fit_array"):
            raise ConfigError(f"{self.name}: noise_fit_array is not supported; use "
                              f"fourier_filter")
        self.filter_specs = cfg.get("filters") or [{
            "name": cfg.get("filt_function", "high_pass_butter4"),
            "filter_params": cfg.get("filter_params", None)}]
        for spec in self.filter_specs:
            if not hasattr(tod_ops.filters, str(spec.get("name"))):
                raise ConfigError(f"{self.name}: no filter {spec.get('name')!r} in "
                                  f"sotodlib.tod_ops.filters")
        self.trim_samps = cfg.get("trim_samps")

    def filter_chain(self):
        """The configured filters as one sotodlib ``FilterChain``."""
        filters = []
        for spec in self.filter_specs:
            params = tod_ops.fft_ops.build_filt_params_dict(
                spec["name"], noise_fit=None, filter_params=spec.get("filter_params"))
            filters.append(getattr(tod_ops.filters, spec["name"])(**params))
        return tod_ops.filters.FilterChain(filters)

    def process(self, aman, proc_aman, sim=False, data_aman=None):
        if data_aman is not None:
            raise NotImplementedError("No support for using data AxisManager in process")
        where = f"{self.name}: {GroupName(aman)}"
        require(aman, self.name, [self.signal_name])
        filt = self.filter_chain()
        fields = list(dict.fromkeys([self.signal_name] + [
            path for spec in self.filter_specs
            for path in _field_paths(aman, spec["name"], spec.get("filter_params"))]))
        signal = aman[self.signal_name]
        if tuple(aman._assignments[self.signal_name]) != (aman.dets.name, aman.samps.name):
            raise ValueError(f"{where}: {self.signal_name} is not (dets, samps); use "
                             f"fourier_filter")
        ndet, nsamp = signal.shape
        in_place = self.wrap_name == self.signal_name and signal.dtype == np.float32
        out = signal if in_place else np.empty((ndet, nsamp), np.float32)
        n = tod_ops.fft_ops.find_superior_integer(nsamp)
        ffts = {}
        for sl in chunks(ndet, self.chunk_dets):
            rows = sl.stop - sl.start
            if rows not in ffts:
                ffts = {rows: tod_ops.fft_ops.RFFTObj.for_shape(rows, n, "BOTH")}
            try:
                out[sl] = tod_ops.filters.fourier_filter(
                    chunk_aman(aman, sl, fields), filt, signal_name=self.signal_name,
                    rfft=ffts[rows])
            except (KeyError, ValueError) as exc:
                raise ValueError(f"{where}: {exc}") from exc
        if not in_place:
            if self.wrap_name in aman._fields:
                aman.move(self.wrap_name, None)
            aman.wrap(self.wrap_name, out, [(0, "dets"), (1, "samps")])
        if self.trim_samps:
            trim = self.trim_samps
            aman.restrict("samps", (aman.samps.offset + trim,
                                    aman.samps.offset + aman.samps.count - trim))
            proc_aman.restrict("samps", (proc_aman.samps.offset + trim,
                                         proc_aman.samps.offset + proc_aman.samps.count - trim))
        return aman, proc_aman


def chunked_glitch_flags(aman, chunk_dets=ChunkConfig.chunk_dets, **calc):
    """sotodlib's ``get_glitch_flags(aman, merge=False, full_output=True, **calc)`` computed
    on chunks of ``chunk_dets`` detectors: the same ``(flags, glitches)`` (a RangesMatrix and
    an AxisManager of ``glitch_flags`` and the sparse ``glitch_detection``)."""
    signal_name = calc.get("signal_name") or "signal"
    fields = [signal_name] + (["flags.left_scan"] if calc.get("subscan") else [])
    flags, detections = [], []
    for sl in chunks(aman.dets.count, chunk_dets):
        _, part = tod_ops.flags.get_glitch_flags(chunk_aman(aman, sl, fields), merge=False,
                                                 full_output=True, **calc)
        flags.extend(part.glitch_flags.ranges)
        detections.append(part.glitch_detection)
    flag = RangesMatrix(flags, child_shape=(aman.samps.count,))
    matrix = (scipy.sparse.csr_array(scipy.sparse.vstack(detections, format="csr"))
              if detections else scipy.sparse.csr_array((0, aman.samps.count)))
    glitches = core.AxisManager(aman.dets, aman.samps)
    glitches.wrap("glitch_flags", flag, [(0, "dets"), (1, "samps")])
    glitches.wrap("glitch_detection", matrix, [(0, "dets"), (1, "samps")])
    return flag, glitches


@_register
class TransientGlitches(GlitchDetection):
    """sotodlib's ``glitches`` step (the same ``calc``, ``save``, ``select`` and ``plot``
    keys, the same flags and significances in ``aman`` and the archive) with
    ``get_glitch_flags`` run on chunks of ``chunk_dets`` detectors (``calc:`` key,
    :class:`ChunkConfig`): sotodlib's step holds the high-passed signal, its absolute value,
    a mask and a threshold for every sample at once (3.7 times the signal for one hour of an
    f090 wafer-band, the production pipeline's peak).

    Config block (in place of ``glitches``)::

      - name: transient_glitches
        calc: {t_glitch: 0.00001, buffer: 10, hp_fc: 1.0, n_sig: 10, subscan: false}
        save: true
    """

    name = "transient_glitches"
    spec = StepSpec(configs=(ChunkConfig,),
                    requires=("timestamps",))

    def __init__(self, step_cfgs):
        super().__init__(step_cfgs)
        calc = dict(self.calc_cfgs or {})
        self.chunk_dets = chunk_setting(self.name, calc)
        self.glitch_calc = calc

    def calc_and_save(self, aman, proc_aman):
        require(aman, self.name, [self.glitch_calc.get("signal_name") or "signal"])
        _, glitch_aman = chunked_glitch_flags(aman, self.chunk_dets, **self.glitch_calc)
        aman.wrap(self.glitch_name, glitch_aman)
        self.save(proc_aman, glitch_aman)
        return aman, proc_aman
