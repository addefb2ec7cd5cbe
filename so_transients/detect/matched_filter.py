"""Per-detector matched filter for point-source crossings (Clancy et al. 2025, section 3.2, eq. 2).

For every detector the filter is

    H(f) = B_hp(f) T(f) / S_n(f)

with ``S_n`` the noise power spectrum estimated from the detector's own spectrum (smoothed in
logarithmic frequency bins), ``B_hp`` a zero-phase Butterworth high-pass of order 4 at the
atmospheric knee, and ``T`` the spectrum of a Gaussian of the beam's width in time
(``sigma_t = sigma_beam / scan speed``). One forward and one inverse real FFT per detector do
all the work: the PSD and the filtering come from the same spectrum. The rest (edge-line
removal, binned PSD, weighting, normalization) is fused into single passes over chunks of
detectors small enough to stay in cache (:mod:`so_transients.detect.spectral_ops`), so the filter runs
close to the cost of the FFTs alone; ``workers`` threads filter chunks in parallel.

Outputs per sample: the amplitude estimate ``A(t)`` in the signal's units (a Gaussian crossing
of peak A gives ``A`` at its centre) and the S/N, ``A(t) / sigma_A``. The S/N is normalized by
its measured robust standard deviation (1.4826 x MAD over valid samples), so its noise has unit
variance by measurement, not by assumption; the analytic expectation is kept for comparison.

Samples that are not finite or are masked are filled by linear interpolation before the FFT;
the S/N and amplitude are set to zero there, within ``mask_buffer`` seconds of them, and within
``edge_buffer`` seconds of either end, so edges and flagged samples never create detections.
Dead detectors get zero S/N and ``dead = True``: those with no finite, non-constant samples,
and those whose white-noise level is below ``min_noise_ratio`` or above ``max_noise_ratio``
times the median of their group's (detectors of one band): a row of zeros that upstream
filtering turned into ~1e-17 of numerical noise would otherwise weigh 1e30 times more than a
real detector in every fit; a dead channel that still carries its readout's jumps and a little
of the common modes upstream filters subtracted records a few per cent of a live detector's
noise, and each would weigh as much as hundreds of live detectors (an optical detector's
noise scatters by some 25 % between detectors, so 0.3 of the median is 5 sigma below it); and
a detector ten times noisier than the rest adds mostly noise to the clustering. The same range
holds for the noise that weighs, the spread of the filtered amplitude (``sigma_amp``): a dead
channel that records only its readout's jumps and cosmic rays has a white-band level a third
of a live detector's but an amplitude spread a thousand times smaller, and three such channels
would carry 99 % of a wafer's weight (:func:`noise_outliers`). They are left
out of the median PSD the kernels are computed from. ``excluded`` says why each is left out
(:data:`EXCLUDED`) and ``masked_fraction`` how much of each detector's time is not searched.

The PSD is estimated from data that contain any sources. A source therefore weights itself
down by its share of the power in the frequencies the filter uses: about S/N^2 / n_eff, with
n_eff the effective number of such frequencies (~13 Hz x duration at f090), so 1.3 % for S/N 10
in a 10-minute TOD but far more for very bright sources or short TODs. Detectors where this
estimate exceeds ``bright_bias`` are filtered a second time, with their PSD re-estimated after
the bright samples are interpolated over, and their S/N scale measured on the same data
without the source, whose filtered response, seconds wide, would otherwise widen it; this
costs three more FFTs for those detectors only (the data's spectrum is kept from the first pass
and weighted again). Each thread filters its
chunks in buffers it reuses (:meth:`_Spectral.workspace`): the only fresh memory is the S/N.
"""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.fft
from tqdm.auto import tqdm

from so_transients.detect import spectral_ops
from so_transients.common.angles import ARCMIN
from so_transients.common.bands import PAPER_KNEE_HZ, nominal_fwhm_arcmin
from so_transients.common.robust import mad_std
from so_transients.common.step_config import non_negative, positive, setting
from so_transients.detect.jumps import remove_jumps

try:        # scipy's own FFTs, writing into arrays given to them
    from scipy.fft._pocketfft.pypocketfft import c2r as _c2r, r2c as _r2c
except ImportError:                   # pragma: no cover - another scipy layout
    _c2r = _r2c = None


def rfft_rows(x, out):
    """``scipy.fft.rfft(x, axis=1)`` written into ``out`` (complex64 for float32 ``x``)."""
    if _r2c is None:                  # pragma: no cover
        out[...] = scipy.fft.rfft(x, axis=1, workers=1)
        return out
    return _r2c(x, (1,), True, 0, out, 1)


def irfft_rows(spec, nfft, out):
    """``scipy.fft.irfft(spec, n=nfft, axis=1)`` written into ``out``; ``spec`` unchanged."""
    if _c2r is None:                  # pragma: no cover
        out[...] = scipy.fft.irfft(spec, n=nfft, axis=1, workers=1)
        return out
    return _c2r(spec, (1,), nfft, False, 2, out, 1)


@dataclass
class FilterConfig:
    """Parameters of :func:`matched_filter` (times in seconds, frequencies in Hz), and of the
    ``transient_filter`` step around it (band field, beam widths, masked flags)."""

    highpass: float | str | None = setting(
        PAPER_KNEE_HZ, "Hz",
        "high-pass frequency of the 4th-order Butterworth (the atmospheric knee); \"fit\": a knee fitted per "
        "detector")
    order: int = setting(4, "", "Butterworth order")
    white_band: tuple = setting((10.0, 30.0), "Hz", "band where the PSD is white, for the noise level")
    bins_per_decade: int = setting(40, "", "PSD smoothing: bins per decade of frequency")
    edge_buffer: float = setting(5.0, "s", "at each end of the TOD where nothing is detected")
    mask_buffer: float = setting(
        0.2, "s",
        "around masked or non-finite samples where nothing is detected")
    chunk_dets: int = setting(16, "", "detectors per FFT batch (kept in cache)")
    bright_bias: float | None = setting(
        0.02, "",
        "detectors whose own source may bias their PSD by more than this fraction are filtered again with it"
        " masked (null: never)")
    source_mask_snr: float = setting(
        3.0, "",
        "detectors filtered again (bright_bias) have their PSD re-estimated with the samples above this S/N "
        "masked")
    workers: int = setting(1, "", "threads, each filtering its own chunks")
    knee_bounds: tuple = setting((0.05, 10.0), "Hz", "limits of a fitted knee")
    min_noise_ratio: float = setting(0.3, "", "detectors quieter than this x the median: dead")
    max_noise_ratio: float = setting(5.0, "", "detectors noisier than this x the median: not used")
    max_excluded: float = setting(
        0.3, "",
        "warn, naming the group, when more than this fraction of its detectors cannot be used")
    jump_threshold: float | None = setting(
        8.0, "",
        "readout jumps (steps of a detector's median level, this many times its spread) are removed before "
        "filtering; null: not looked for (so_transients.detect.jumps)")
    jump_window: float = setting(2.0, "s", "of median level compared on each side of a jump")
    bandpass_field: str = setting("bandpass", "", "det_info field holding each detector's band")
    beam_fwhm_arcmin: dict = setting(
        unit="arcmin",
        doc="beam FWHM per band; nominal ones for the bands it does not name",
        default_factory=dict)
    mask_flags: list = setting(unit="", doc="aman.flags fields to ignore", default_factory=list)

    def __post_init__(self):
        if self.highpass == "fit":
            self.highpass = None
        elif self.highpass is not None:
            try:
                self.highpass = float(self.highpass)
            except ValueError:
                raise ValueError(f"highpass must be a frequency in Hz or 'fit', got "
                                 f"{self.highpass!r}") from None
            if not self.highpass > 0:
                raise ValueError(f"highpass must be a positive frequency in Hz or 'fit', got "
                                 f"{self.highpass}")
        for key in ("order", "bins_per_decade", "chunk_dets", "workers", "min_noise_ratio",
                    "max_noise_ratio", "max_excluded", "jump_window"):
            if not getattr(self, key) > 0:
                raise ValueError(f"{key} must be positive, got {getattr(self, key)}")
        non_negative("transient_filter", edge_buffer=self.edge_buffer,
                     mask_buffer=self.mask_buffer)
        positive("transient_filter", bright_bias=self.bright_bias,
                 source_mask_snr=self.source_mask_snr)
        if self.max_excluded > 1 or (self.jump_threshold is not None
                                     and not self.jump_threshold > 0):
            raise ValueError(f"max_excluded must be at most 1 and jump_threshold positive or "
                             f"null, got {self.max_excluded}, {self.jump_threshold}")
        self.white_band = tuple(self.white_band)
        unknown = sorted(set(self.beam_fwhm_arcmin) - set(nominal_fwhm_arcmin()))
        if unknown:
            raise ValueError(f"beam_fwhm_arcmin: unknown band(s) {unknown}; known: "
                             f"{sorted(nominal_fwhm_arcmin())}")
        for band, fwhm in self.beam_fwhm_arcmin.items():
            if isinstance(fwhm, bool) or not isinstance(fwhm, (int, float)) or fwhm <= 0:
                raise ValueError(f"beam_fwhm_arcmin: {band} must be a positive number of "
                                 f"arcmin, got {fwhm!r}")

    def beam_fwhm(self, bands):
        """Beam FWHM (radians) of detectors in ``bands``: the config's ``beam_fwhm_arcmin``
        where it names the band, else the nominal one."""
        table = {**nominal_fwhm_arcmin(), **self.beam_fwhm_arcmin}
        unknown = sorted(set(bands) - set(table))
        if unknown:
            raise ValueError(f"no beam FWHM configured for bandpass {unknown}; add it to "
                             f"beam_fwhm_arcmin")
        return np.array([table[b] for b in bands], float) * ARCMIN


@dataclass
class FilterResult:
    """Outputs of :func:`matched_filter`.

    ``snr`` is the only per-sample array (float32, (ndet, nsamps)): zero wherever nothing may
    be detected (edges, masked samples, dead detectors). The amplitude timestream is
    ``snr * sigma_amp`` per detector (:attr:`amplitude` computes it), so it costs no memory.
    """

    snr: np.ndarray
    noise_level: np.ndarray                 # white noise per sample, signal units
    fknee: np.ndarray                       # high-pass frequency used (fixed or fitted), Hz
    sigma_amp: np.ndarray                   # noise of the amplitude timestream, signal units
    snr_scale: np.ndarray                   # measured / analytic S/N standard deviation
    dead: np.ndarray
    median_psds: dict = field(default_factory=dict)   # group -> median smoothed PSD of its
    #                                                   live rows (|X|^2 units)
    nfft: int = 0
    psd_bins: np.ndarray = field(default=None)     # (ndet, nbins) binned PSD each row used
    psd_edges: np.ndarray = field(default=None)    # rfft indices of the bins' edges
    snr_factor: np.ndarray = field(default=None)   # S/N = filtered signal x snr_factor
    excluded: np.ndarray = field(default=None)     # why each dead detector is not used
    #                                                (:data:`EXCLUDED`; 0: used)
    masked_fraction: np.ndarray = field(default=None)  # of each detector's samples not finite,
    #                                                    masked, or within mask_buffer of those
    n_jumps: np.ndarray = field(default=None)      # readout jumps removed from each detector
    n_eff: np.ndarray = field(default=None)        # effective number of frequencies each row's
    #                       first pass used (:meth:`_Spectral.apply`), which decides its second
    #                       pass (S/N^2 / n_eff above ``bright_bias``); NaN for dead detectors

    @property
    def valid(self):
        """Samples that may be detected (bool, (ndet, nsamps))."""
        return self.snr != 0

    @property
    def amplitude(self):
        """Amplitude estimate A(t) in signal units (float32, (ndet, nsamps))."""
        return self.snr * self.sigma_amp[:, None].astype(np.float32)


def gaussian_template_spectrum(nfft, sample_rate, sigma_t):
    """Real spectrum (rfft) of a unit-peak Gaussian of width ``sigma_t`` centred on sample 0."""
    n = np.arange(nfft)
    lag = np.minimum(n, nfft - n) / sample_rate
    return scipy.fft.rfft(np.exp(-0.5 * (lag / sigma_t) ** 2)).real


def butterworth_highpass(freqs, fc, order=4):
    """Magnitude of a zero-phase Butterworth high-pass; ``fc`` broadcasts against ``freqs``."""
    with np.errstate(divide="ignore"):
        ratio = np.where(freqs > 0, (np.asarray(fc)[..., None] / np.maximum(freqs, 1e-300)), np.inf)
    return 1.0 / np.sqrt(1.0 + ratio ** (2 * order))


def _log_bins(nf, bins_per_decade):
    """Edges of log-spaced frequency bins over rfft indices 1 .. nf (DC excluded)."""
    decades = np.log10(max(nf - 1, 1))
    edges = np.unique(np.round(np.logspace(0, decades, int(decades * bins_per_decade) + 2)))
    edges = edges[edges < nf].astype(np.int64)
    return np.concatenate([[1], edges[edges > 1], [nf]]).astype(np.int64)


def expand_bins(binned, edges):
    """Per-frequency array (rfft length) from per-bin values; DC gets the first bin's value."""
    binned = np.atleast_2d(binned)
    full = np.repeat(binned, np.diff(edges), axis=1)
    return np.concatenate([binned[:, :1], full], axis=1)


def fit_knee(freqs, psd, white, bounds=(0.05, 10.0), white_lo=10.0, counts=None):
    """Knee of ``white * (1 + (fknee/f)^alpha)`` fitted to a smoothed PSD, per detector.

    Linear fit of ``log(P/white - 1)`` against ``log f`` where the red part is well above and
    the white part not yet dominant; ``fknee`` is where the fitted red power equals white.
    ``counts``: number of frequencies each PSD value stands for (binned PSDs), as fit weights.
    """
    out = np.full(len(psd), np.nan)
    sel_f = (freqs > 0) & (freqs < white_lo)
    logf = np.log(freqs[sel_f])
    weight = np.sqrt(np.ones(len(freqs)) if counts is None else counts)[sel_f]
    for i in range(len(psd)):
        excess = psd[i, sel_f] / white[i] - 1
        ok = (excess > 0.3) & (excess < 1e4)
        if ok.sum() < 5:
            continue
        slope, offset = np.polyfit(logf[ok], np.log(excess[ok]), 1, w=weight[ok])
        if slope < 0:
            out[i] = np.exp(-offset / slope)
    return np.clip(out, *bounds)


def _fill_bad(x, bad):
    """Linear interpolation across bad samples of the rows of ``x``, in place."""
    spectral_ops.interpolate_runs(x, np.ascontiguousarray(bad))


def _grow(bad, n):
    """``bad`` (rows, nsamp) widened by ``n`` samples on each side."""
    return spectral_ops.dilate_rows(np.ascontiguousarray(bad), n) if n else bad


class _Spectral:
    """What every detector chunk shares: FFT length, PSD bins, line spectra, templates."""

    def __init__(self, nsamp, sample_rate, sigma_t, cfg):
        self.nsamp, self.cfg, self.sample_rate = nsamp, cfg, sample_rate
        self._local = threading.local()       # each thread's buffers (workspace)
        self.nfft = scipy.fft.next_fast_len(nsamp, real=True)
        self.freqs = scipy.fft.rfftfreq(self.nfft, 1.0 / sample_rate)
        self.weight = np.full(len(self.freqs), 2.0)
        self.weight[0] = 1.0
        if self.nfft % 2 == 0:
            self.weight[-1] = 1.0
        white_sel = ((self.freqs >= cfg.white_band[0])
                     & (self.freqs <= min(cfg.white_band[1], self.freqs[-1])))
        if not white_sel.any():
            raise ValueError(f"white_band {cfg.white_band} Hz is outside the spectrum "
                             f"(Nyquist {self.freqs[-1]:.1f} Hz)")
        self.edges = _log_bins(len(self.freqs), cfg.bins_per_decade)
        # frequencies of the white band in each bin, for the white level
        self.white_weight = np.add.reduceat(white_sel[1:].astype(float), self.edges[:-1] - 1)
        self.bin_counts = np.diff(self.edges)
        self.bin_freqs = np.exp(np.add.reduceat(np.log(self.freqs[1:]), self.edges[:-1] - 1)
                                / self.bin_counts)
        self.n_edge = int(round(cfg.edge_buffer * sample_rate))
        self.n_line = max(1, min(nsamp // 4, int(round(sample_rate))))
        # the spectra of a constant and of a 0..1 ramp over the data: a line removed in Fourier
        # space is the same as removing it before the FFT, without another pass over the data
        self.f_ones, self.f_ramp = (
            scipy.fft.rfft(v, n=self.nfft).astype(np.complex64).view(np.float32)
            for v in (np.ones(nsamp), np.linspace(0.0, 1.0, nsamp)))
        self.sigmas = np.unique(sigma_t)
        self.templates = [gaussian_template_spectrum(self.nfft, sample_rate, s)
                          for s in self.sigmas]
        self.fixed = None
        if cfg.highpass is not None:
            hp = butterworth_highpass(self.freqs, float(cfg.highpass), cfg.order)
            self.fixed = self._bases(hp[None, :], np.arange(len(self.sigmas)))

    def _bases(self, hp, template_index):
        """Weights ``hp T`` per row (or per template) and their bin sums for the normalization."""
        tmpl = np.stack([self.templates[j] for j in template_index])
        base = hp * tmpl
        w = self.weight
        binned = lambda v: np.add.reduceat(v[:, 1:], self.edges[:-1] - 1, axis=1)
        bt = binned(w * base * tmpl)
        return base, bt, binned(w * base**2), binned((w * base * tmpl) ** 2)

    def workspace(self):
        """This thread's buffers for a chunk of up to ``cfg.chunk_dets`` rows, made on its
        first chunk and reused for every later one (fresh memory costs several passes over
        it on first touch): ``x`` and ``x2`` (padded data, their padding zero), ``spec``,
        ``spec2`` and ``weighted`` (spectra), ``y`` (the filtered rows)."""
        local = self._local
        if not hasattr(local, "buffers"):
            rows, nf = self.cfg.chunk_dets, len(self.freqs)
            local.buffers = {
                **{k: np.zeros((rows, self.nfft), np.float32) for k in ("x", "x2", "y")},
                **{k: np.empty((rows, nf), np.complex64) for k in ("spec", "spec2", "weighted")}}
        return local.buffers

    def spectrum(self, x, out):
        """rfft of the padded rows ``x`` (into ``out``) with the edge line removed, and their
        binned PSD."""
        spec = rfft_rows(x, out)
        n = self.n_line
        a = x[:, :n].mean(axis=1, dtype=float)
        c = x[:, self.nsamp - n:self.nsamp].mean(axis=1, dtype=float) - a
        psd = np.empty((len(x), len(self.edges) - 1))
        spectral_ops.remove_line_and_bin(spec.view(np.float32), a, c, self.f_ones, self.f_ramp,
                                         self.edges, psd)
        white = psd @ self.white_weight / self.white_weight.sum()
        return spec, psd, white

    def apply(self, spec, psd, white, sigma_t, weighted, y):
        """Filter ``spec`` (its weighted copy into ``weighted``, which may be ``spec`` itself;
        the filtered rows into ``y``); returns ``y`` (rows, nfft) and per row the amplitude
        normalization, Var(y), the high-pass frequency and the effective number of frequencies
        the filter uses, ``(sum c_f)^2 / sum c_f^2`` with ``c_f`` each frequency's share of the
        S/N^2 (how much a source's own power can bias its PSD, see :func:`_filter_chunk`)."""
        cfg = self.cfg
        tmpl_index = np.searchsorted(self.sigmas, sigma_t)
        if self.fixed is None:
            fknee = fit_knee(self.bin_freqs, psd, white, cfg.knee_bounds, cfg.white_band[0],
                             self.bin_counts)
            fknee[np.isnan(fknee)] = cfg.knee_bounds[0]
            base, bt, b2, bt2 = self._bases(butterworth_highpass(self.freqs, fknee, cfg.order),
                                            tmpl_index)
            base_index = np.arange(len(psd))
        else:
            fknee = np.full(len(psd), float(cfg.highpass))
            base, bt, b2, bt2 = self.fixed
            base_index = tmpl_index
        inv = 1.0 / psd
        norm = np.einsum("ik,ik->i", inv, bt[base_index]) / self.nfft
        var_y = np.einsum("ik,ik->i", inv, b2[base_index]) / self.nfft**2
        n_eff = (norm * self.nfft) ** 2 / np.einsum("ik,ik->i", inv**2, bt2[base_index])
        spectral_ops.weight_spectrum(spec, base, base_index, inv, self.edges, weighted)
        irfft_rows(weighted, self.nfft, y)
        return y, norm, var_y, fknee, n_eff

    def robust_sigma(self, y, grown):
        """Robust standard deviation of each row of ``y`` over its searchable samples."""
        n0, n1 = self.n_edge, self.nsamp - self.n_edge
        if n1 - n0 < 20:
            n0, n1 = 0, self.nsamp
        stride = max(7, (n1 - n0) // 10000)
        idx = np.arange(n0, n1, stride)
        values = y[:, idx]
        out = mad_std(values, axis=1).astype(float)
        for i, row in grown.items():
            good = values[i][~row[idx]]
            out[i] = mad_std(good) if good.size > 10 else np.nan
        return out


@dataclass
class _Chunk:
    """One chunk's per-detector results and the smoothed PSDs of its live detectors."""

    sl: slice
    fknee: np.ndarray
    snr_factor: np.ndarray
    psd_all: np.ndarray
    sigma_amp: np.ndarray
    snr_scale: np.ndarray
    noise_level: np.ndarray
    dead: np.ndarray
    psd: np.ndarray
    masked_fraction: np.ndarray
    n_jumps: np.ndarray
    n_eff: np.ndarray


def _prepare(sp, signal_rows, mask_rows, buffer):
    """Padded float32 copy of the rows in ``buffer`` (rows, nfft; its padding zero), bad
    (non-finite or masked) samples interpolated over; and the bad samples ((rows, nsamp)
    bool, or None when there are none)."""
    x = buffer[:, :sp.nsamp]
    x[...] = signal_rows
    bad = None
    if not np.isfinite(x.sum(axis=1)).all():
        bad = ~np.isfinite(x)
        x[bad] = 0.0
    if mask_rows is not None and np.any(mask_rows):
        bad = np.asarray(mask_rows, bool) | (bad if bad is not None else False)
    if bad is not None:
        _fill_bad(x, bad)
    return buffer, bad


def _filter_rows(sp, spec, noise, bad_rows, sigma_t, out_snr, rows, weighted, y,
                 source_free=None):
    """Filter the spectra ``spec`` (:meth:`_Spectral.spectrum`) with the noise model ``noise``
    (binned PSD, white level) into ``out_snr[rows]`` (S/N); returns per-row results and peak
    |S/N|. ``weighted``, ``y``: buffers for the weighted spectra (``spec`` itself when it
    is not needed again) and the filtered rows.

    ``bad_rows``: {row: grown bad-sample mask} of rows with samples that must not be detected.
    ``source_free``: ``(spectra, buffer)``: the same rows with their bright source
    interpolated over, and a buffer for them filtered; the S/N scale is measured on those
    (a bright source's response, seconds wide, would otherwise widen its row's measured noise).
    """
    psd, white = noise
    dead = white <= 0
    for i, row in bad_rows.items():
        dead[i] |= row.all()
    psd, live_white = np.where(dead[:, None], 1.0, psd), np.where(dead, 1.0, white)
    y, norm, var_y, fknee, n_eff = sp.apply(spec, psd, live_white, sigma_t, weighted, y)
    if source_free is None:
        measured = sp.robust_sigma(y, bad_rows)
    else:
        free_spec, free_y = source_free
        measured = sp.robust_sigma(sp.apply(free_spec, psd, live_white, sigma_t, free_spec,
                                            free_y)[0], bad_rows)
    sigma_y = np.sqrt(var_y)
    ok = np.isfinite(measured) & (measured > 0)
    scale = np.where(ok, measured / sigma_y, 1.0)
    factor = np.where(dead, 0.0, 1.0 / (sigma_y * scale)).astype(np.float32)
    peak = spectral_ops.scale_rows(y, factor, sp.n_edge, out_snr, rows)
    for i, row in bad_rows.items():
        out_snr[rows[i], row] = 0.0
        peak[i] = np.abs(out_snr[rows[i]]).max()
    return dict(psd=psd, white=white, dead=dead, fknee=fknee, scale=scale, n_eff=n_eff,
                snr_factor=factor,
                sigma_amp=np.where(dead, 0.0, sigma_y * scale / norm)), peak


def _source_masked_psd(sp, x, snr, sigma_t, spec):
    """Binned PSD of rows ``x`` (a copy: overwritten; ``spec`` a buffer for its spectrum, left
    holding it) with samples above ``source_mask_snr``
    (and 2 sigma_t around them) interpolated over: the noise without the source. Interpolated
    samples carry no white noise, so the PSD is scaled up by the masked fraction (a constant
    factor per row changes neither the S/N nor the amplitude, only the white level)."""
    width = int(np.ceil(2 * np.max(sigma_t) * sp.sample_rate))
    masked = spectral_ops.interpolate_above(x, snr, np.float32(sp.cfg.source_mask_snr), width)
    _, psd, white = sp.spectrum(x, spec)
    kept = np.clip(1.0 - masked / sp.nsamp, 0.5, 1.0)
    return psd / kept[:, None], white / kept


def _filter_chunk(sp, signal, mask, sigma_t, sl, out_snr):
    """Filter the detectors ``sl``; a second pass for rows holding a bright source.

    A source adds its own power to its detector's PSD and so weights itself down, by about
    ``S/N^2 / n_eff`` of the power in the frequencies the filter uses (``n_eff`` of them, see
    :meth:`_Spectral.apply`): 0.7 % for S/N 10 in 20 minutes at f090. Rows where this exceeds
    ``bright_bias`` are filtered again with their PSD estimated with the source masked.
    """
    cfg = sp.cfg
    ws = {k: v[:sl.stop - sl.start] for k, v in sp.workspace().items()}
    x, bad = _prepare(sp, signal[sl], None if mask is None else mask[sl], ws["x"])
    n_jumps = (remove_jumps(x[:, :sp.nsamp], sp.sample_rate, cfg.jump_window,
                            threshold=cfg.jump_threshold)
               if cfg.jump_threshold is not None else np.zeros(len(x), int))
    n_mask = int(round(cfg.mask_buffer * sp.sample_rate))
    bad_rows = ({} if bad is None else
                {i: _grow(bad[i:i + 1], n_mask)[0] for i in np.flatnonzero(bad.any(axis=1))})
    snr = out_snr[sl]
    spec, psd, white = sp.spectrum(x, ws["spec"])
    second = cfg.bright_bias is not None
    # with a second pass in view, the spectra are kept: weighted into a copy
    res, peak = _filter_rows(sp, spec, (psd, white), bad_rows, sigma_t[sl], snr,
                             np.arange(len(x)), ws["weighted"] if second else spec, ws["y"])
    bright = (np.flatnonzero((peak**2 / res["n_eff"] > cfg.bright_bias) & ~res["dead"])
              if second else [])
    if len(bright):
        # the same spectra weighted with the PSD of the rows with their source masked
        n = len(bright)
        row_sigma_t = sigma_t[sl][bright]
        noise = _source_masked_psd(sp, np.take(x, bright, axis=0, out=ws["x2"][:n]),
                                   snr[bright], row_sigma_t, ws["weighted"][:n])
        sub_bad = {j: bad_rows[i] for j, i in enumerate(bright) if i in bad_rows}
        rows_spec = np.take(spec, bright, axis=0, out=ws["spec2"][:n])
        again, _ = _filter_rows(sp, rows_spec, noise, sub_bad, row_sigma_t, snr, bright,
                                rows_spec, ws["y"][:n],
                                source_free=(ws["weighted"][:n], ws["x2"][:n]))
        for key, value in again.items():
            if key != "n_eff":         # kept as the first pass measured it: what decided
                res[key][bright] = value
    dead = res["dead"]
    return _Chunk(sl, res["fknee"], res["snr_factor"], res["psd"].astype(np.float32),
                  res["sigma_amp"], np.where(dead, np.nan, res["scale"]),
                  np.where(dead, 0.0, np.sqrt(res["white"] / sp.nsamp)), dead,
                  res["psd"][~dead],
                  np.array([bad_rows[i][:sp.nsamp].mean() if i in bad_rows else 0.0
                            for i in range(len(dead))]), n_jumps,
                  np.where(dead, np.nan, res["n_eff"]))


#: Why a detector is not used, as ``FilterResult.excluded`` (and the archive) codes it
EXCLUDED = {0: "used", 1: "no finite, non-constant data", 2: "noise below min_noise_ratio",
            3: "noise above max_noise_ratio",
            4: "amplitude noise outside min/max_noise_ratio (its noise is not Gaussian)"}
NO_DATA, QUIET, NOISY, NON_GAUSSIAN = 1, 2, 3, 4
#: The same codes as column names
EXCLUDED_NAMES = {NO_DATA: "no_data", QUIET: "too_quiet", NOISY: "too_noisy",
                  NON_GAUSSIAN: "non_gaussian"}


def _ratio_to_median(level, live_groups):
    """``level`` over the median of its group's live rows (``live_groups``: {group: rows});
    rows of numerical noise (zeros filtered upstream) do not set the median."""
    ratio = np.full(len(level), np.nan)
    for live in live_groups.values():
        values = level[live]
        reference = np.median(values[values > 1e-6 * np.percentile(values, 75)])
        ratio[live] = values / reference
    return ratio


def noise_outliers(noise_level, sigma_amp, dead, groups, cfg: FilterConfig):
    """Live detectors whose noise is out of their group's range, judged on both noise
    measures against the median of the group's live detectors: the white-band level below
    ``cfg.min_noise_ratio`` (:data:`QUIET`) or above ``cfg.max_noise_ratio`` (:data:`NOISY`)
    times it; then the spread of the filtered amplitude, ``sigma_amp``, which sets each
    detector's weight in every fit and map, outside the same range (:data:`NON_GAUSSIAN`).
    A dead channel that records only its readout's jumps and cosmic rays has a white level
    a third of a live detector's but an amplitude spread a thousand times smaller, and
    would otherwise carry nearly all of the wafer's weight. 0 for the others."""
    out = np.zeros(len(noise_level), np.int8)
    live_groups = {g: np.flatnonzero((groups == g) & ~dead) for g in np.unique(groups)}
    live_groups = {g: rows for g, rows in live_groups.items() if len(rows)}
    outside = lambda ratio: (ratio < cfg.min_noise_ratio) | (ratio > cfg.max_noise_ratio)
    white = _ratio_to_median(noise_level, live_groups)
    amp = _ratio_to_median(sigma_amp, live_groups)
    live = np.isfinite(white)
    out[live] = np.where(white[live] < cfg.min_noise_ratio, QUIET,
                         np.where(white[live] > cfg.max_noise_ratio, NOISY,
                                  np.where(outside(amp[live]), NON_GAUSSIAN, 0)))
    return out


def _exclude(result: FilterResult, rows):
    """Mark ``rows`` dead in ``result``: no S/N, no amplitude noise, no weight."""
    result.snr[rows] = 0.0
    result.dead[rows] = True
    result.sigma_amp[rows] = 0.0
    result.snr_factor[rows] = 0.0
    result.snr_scale[rows] = np.nan
    result.n_eff[rows] = np.nan


def matched_filter(signal, sample_rate, sigma_t, cfg: FilterConfig = FilterConfig(),
                   mask=None, progress=False, groups=None) -> FilterResult:
    """Matched-filter every detector of ``signal`` (ndet, nsamps); see the module docstring.

    ``sigma_t``: template width in seconds, scalar or per detector. ``mask``: optional bool
    array (ndet, nsamps) of samples to ignore. ``groups``: optional label per detector (its
    band) within which noise levels are compared. The input array is not modified. Chunks of
    ``cfg.chunk_dets`` detectors are filtered in ``cfg.workers`` threads.
    """
    signal = np.asarray(signal)
    if signal.ndim != 2:
        raise ValueError(f"signal must be (ndet, nsamps), got shape {signal.shape}")
    ndet, nsamp = signal.shape
    sigma_t = np.broadcast_to(np.asarray(sigma_t, dtype=float), (ndet,))
    if nsamp < 16:
        raise ValueError(f"only {nsamp} samples: too short to filter")
    sp = _Spectral(nsamp, sample_rate, sigma_t if ndet else np.ones(1), cfg)
    snr = np.zeros((ndet, nsamp), np.float32)
    slices = [slice(s, min(s + cfg.chunk_dets, ndet)) for s in range(0, ndet, cfg.chunk_dets)]
    work = lambda sl: _filter_chunk(sp, signal, mask, sigma_t, sl, snr)
    if cfg.workers > 1:
        with ThreadPoolExecutor(cfg.workers) as pool:
            chunks = list(tqdm(pool.map(work, slices), total=len(slices), disable=not progress,
                               desc="matched filter", unit="chunk"))
    else:
        chunks = [work(sl) for sl in tqdm(slices, disable=not progress, desc="matched filter",
                                          unit="chunk")]
    gather = lambda key: np.concatenate([getattr(c, key) for c in chunks]) if chunks else np.zeros(0)
    result = FilterResult(snr=snr, noise_level=gather("noise_level"), fknee=gather("fknee"),
                          sigma_amp=gather("sigma_amp"), snr_scale=gather("snr_scale"),
                          dead=gather("dead").astype(bool), nfft=sp.nfft,
                          psd_bins=gather("psd_all"), psd_edges=sp.edges,
                          snr_factor=gather("snr_factor"),
                          masked_fraction=gather("masked_fraction"),
                          n_jumps=gather("n_jumps").astype(int), n_eff=gather("n_eff"))
    groups = np.zeros(ndet, int) if groups is None else np.asarray(groups)
    first_dead = result.dead.copy()
    reason = noise_outliers(result.noise_level, result.sigma_amp, first_dead, groups, cfg)
    outliers = reason > 0
    _exclude(result, np.flatnonzero(outliers))
    result.excluded = np.where(first_dead, NO_DATA, reason).astype(np.int8)
    psds = [c.psd for c in chunks if len(c.psd)]
    if psds:      # the live rows' PSDs, in detector order; outliers left out
        live_rows = np.flatnonzero(~first_dead)
        keep = ~outliers[live_rows]
        live_psd, live_groups = np.concatenate(psds)[keep], groups[live_rows][keep]
        for g in np.unique(live_groups):
            rows = live_psd[live_groups == g]
            result.median_psds[g] = expand_bins(np.median(rows, axis=0), sp.edges)[0]
    return result


def response_kernels(result: FilterResult, sample_rate, sigma_t, groups, order=4):
    """The filter's response to a crossing for every detector, from its group's (band's)
    median template width, knee and PSD: ``(lags, response (ndet, nlag), inflation (ndet,))``
    (:func:`filter_kernels`, :func:`fit_error_inflation`). Rows of groups without a live
    detector get a zero response and inflation 1."""
    ndet = len(result.dead)
    if not result.median_psds:
        return np.zeros(1), np.ones((ndet, 1)), np.ones(ndet)
    groups = np.asarray(groups)
    kernels = {}
    for g, psd in result.median_psds.items():
        live = (groups == g) & ~result.dead
        lags, response, acf = filter_kernels(result.nfft, sample_rate,
                                             float(np.median(sigma_t[live])),
                                             float(np.median(result.fknee[live])), psd, order)
        kernels[g] = (lags, response, fit_error_inflation(response, acf))
    lags = next(iter(kernels.values()))[0]
    responses, inflation = np.zeros((ndet, len(lags))), np.ones(ndet)
    for g, (_, response, infl) in kernels.items():
        rows = groups == g
        responses[rows], inflation[rows] = response, infl
    return lags, responses, inflation


def filter_kernels(nfft, sample_rate, sigma_t, fknee, psd, order=4, max_lag=1.0):
    """Response of the filter to a template-shaped crossing, and the noise autocorrelation.

    For the smoothed PSD ``psd`` (rfft length), returns ``(lags, response, acf)`` for lags
    within ``max_lag`` seconds: ``response`` is the amplitude timestream produced by a crossing
    of unit peak centred at lag 0 (1 at lag 0), ``acf`` the correlation of the filtered noise
    between samples ``lag`` apart (1 at lag 0). Both are symmetric (zero-phase filter).
    """
    freqs = scipy.fft.rfftfreq(nfft, 1.0 / sample_rate)
    tmpl = gaussian_template_spectrum(nfft, sample_rate, sigma_t)
    gain = butterworth_highpass(freqs, fknee, order) * tmpl / psd
    gain[0] = 0.0
    response = scipy.fft.irfft(gain * tmpl, n=nfft)
    acf = scipy.fft.irfft(gain**2 * psd, n=nfft)
    n = min(int(round(max_lag * sample_rate)), nfft // 2 - 1)
    idx = np.arange(-n, n + 1)
    return idx / sample_rate, response[idx] / response[0], acf[idx] / acf[0]


def fit_error_inflation(response, acf):
    """Factor by which least-squares errors that treat filtered samples as independent are
    too small, for a fit of the ``response`` shape to noise correlated as ``acf``.

    Var(A_hat) = R^T C R / (R^T R)^2 against the naive 1 / R^T R (unit noise), so the factor is
    sqrt(R^T (rho * R) / R^T R).
    """
    smeared = np.convolve(response, acf, mode="same")
    return float(np.sqrt(max(np.dot(response, smeared) / np.dot(response, response), 1.0)))
