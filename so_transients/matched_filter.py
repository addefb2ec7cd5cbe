"""Per-detector matched filter for point-source crossings (Clancy et al. 2025, section 3.2, eq. 2).

For every detector the filter is

    H(f) = B_hp(f) T(f) / S_n(f)

with ``S_n`` the noise power spectrum estimated from the detector's own spectrum (smoothed in
logarithmic frequency bins), ``B_hp`` a zero-phase Butterworth high-pass of order 4 at the
atmospheric knee, and ``T`` the spectrum of a Gaussian of the beam's width in time
(``sigma_t = sigma_beam / scan speed``). One forward and one inverse real FFT per detector do
all the work: the PSD and the filtering come from the same spectrum.

Outputs per sample: the amplitude estimate ``A(t)`` in the signal's units (a Gaussian crossing
of peak A gives ``A`` at its centre) and the S/N, ``A(t) / sigma_A``. The S/N is normalized by
its measured robust standard deviation (1.4826 x MAD over valid samples), so its noise has unit
variance by measurement, not by assumption; the analytic expectation is kept for comparison.

Samples that are not finite or are masked are filled by linear interpolation before the FFT;
the S/N and amplitude are set to zero there, within ``mask_buffer`` seconds of them, and within
``edge_buffer`` seconds of either end, so edges and flagged samples never create detections.
Dead detectors (no finite, non-constant samples) get zero S/N and ``dead = True``.

The PSD is estimated from data that contain any sources. A source therefore weights itself
down, biasing its own amplitude low by its share of the noise power in the bins it occupies:
about (A T / sigma)^2 / N, below 1 % for a 1.5 Jy f090 crossing in a 10-minute TOD but far more
for very bright sources or short TODs. Detectors whose S/N exceeds ``bright_snr`` are therefore
filtered a second time, with their PSD re-estimated after the bright samples are interpolated
over; this costs one more FFT pair for those few detectors only.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.fft
from scipy import ndimage

MAD_TO_SIGMA = 1.4826


@dataclass
class FilterConfig:
    """Parameters of :func:`matched_filter` (times in seconds, frequencies in Hz)."""

    highpass: float | None = 1.23         # knee frequency; None: fit per detector
    order: int = 4                         # Butterworth order
    white_band: tuple = (10.0, 30.0)       # band where the PSD is white, for the noise level
    bins_per_decade: int = 40              # PSD smoothing
    edge_buffer: float = 5.0
    mask_buffer: float = 0.2
    chunk_dets: int = 64                   # detectors per FFT batch (memory)
    bright_snr: float | None = 10.0        # refilter rows above this S/N with the source masked
    source_mask_snr: float = 3.0           # ... masking samples above this S/N
    workers: int = 1                       # FFT threads
    knee_bounds: tuple = (0.05, 10.0)      # limits of a fitted knee


@dataclass
class FilterResult:
    """Outputs of :func:`matched_filter`; per-sample arrays are float32, (ndet, nsamps)."""

    snr: np.ndarray
    amplitude: np.ndarray
    valid: np.ndarray                       # bool (ndet, nsamps): samples that may be detected
    noise_level: np.ndarray                 # white noise per sample, signal units
    fknee: np.ndarray                       # high-pass frequency used (fixed or fitted), Hz
    sigma_amp: np.ndarray                   # noise of the amplitude timestream, signal units
    snr_scale: np.ndarray                   # measured / analytic S/N standard deviation
    dead: np.ndarray
    median_psd: np.ndarray = field(default=None)   # median smoothed PSD (|X|^2 units)
    freqs: np.ndarray = field(default=None)
    nfft: int = 0


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
    decades = np.log10(max(nf - 1, 1))
    edges = np.unique(np.round(np.logspace(0, decades, int(decades * bins_per_decade) + 2)))
    edges = edges[edges < nf].astype(int)
    return np.concatenate([[1], edges[edges > 1], [nf]])


def smoothed_psd(power, bins_per_decade):
    """Average ``power`` (ndet, nf) in log-spaced frequency bins; DC is kept as is."""
    nf = power.shape[1]
    edges = _log_bins(nf, bins_per_decade)
    sums = np.add.reduceat(power[:, 1:], edges[:-1] - 1, axis=1)
    means = sums / np.diff(edges)[None, :]
    index = np.searchsorted(edges, np.arange(1, nf), side="right") - 1
    out = np.empty_like(power)
    out[:, 0] = power[:, 0]
    out[:, 1:] = means[:, index]
    return out


def fit_knee(freqs, psd, white, bounds=(0.05, 10.0), white_lo=10.0):
    """Knee of ``white * (1 + (fknee/f)^alpha)`` fitted to a smoothed PSD, per detector.

    Linear fit of ``log(P/white - 1)`` against ``log f`` where the red part is well above and
    the white part not yet dominant; ``fknee`` is where the fitted red power equals white.
    """
    out = np.full(len(psd), np.nan)
    sel_f = (freqs > 0) & (freqs < white_lo)
    logf = np.log(freqs[sel_f])
    for i in range(len(psd)):
        excess = psd[i, sel_f] / white[i] - 1
        ok = (excess > 0.3) & (excess < 1e4)
        if ok.sum() < 5:
            continue
        slope, offset = np.polyfit(logf[ok], np.log(excess[ok]), 1)
        if slope < 0:
            out[i] = np.exp(-offset / slope)
    return np.clip(out, *bounds)


def _fill_bad(x, bad):
    """Linear interpolation across bad samples, in place, row by row."""
    for i in np.flatnonzero(bad.any(axis=1)):
        good = ~bad[i]
        if good.sum() < 2:
            x[i] = 0.0
            continue
        idx = np.arange(x.shape[1])
        x[i, ~good] = np.interp(idx[~good], idx[good], x[i, good])


def _remove_edge_line(x, n_edge):
    """Subtract the line through the means of the first and last ``n_edge`` samples."""
    a = x[:, :n_edge].mean(axis=1)
    b = x[:, -n_edge:].mean(axis=1)
    ramp = np.linspace(0.0, 1.0, x.shape[1], dtype=x.dtype)
    x -= a[:, None] + (b - a)[:, None] * ramp[None, :]


def robust_std(x, valid, stride=7):
    """1.4826 x median absolute deviation of the valid samples of each row (subsampled)."""
    out = np.full(len(x), np.nan)
    for i in range(len(x)):
        v = x[i, ::stride][valid[i, ::stride]]
        if v.size > 10:
            out[i] = MAD_TO_SIGMA * np.median(np.abs(v - np.median(v)))
    return out


def _valid_mask(bad, nsamp, sample_rate, cfg):
    valid = np.ones((len(bad), nsamp), bool)
    n_edge = int(round(cfg.edge_buffer * sample_rate))
    if n_edge:
        valid[:, :n_edge] = False
        valid[:, -n_edge:] = False
    n_mask = int(round(cfg.mask_buffer * sample_rate))
    if bad.any():
        grown = ndimage.binary_dilation(bad, structure=np.ones((1, 2 * n_mask + 1), bool)) \
            if n_mask else bad
        valid &= ~grown
    return valid


class _Spectral:
    """What every detector chunk shares: FFT length, frequencies, weights and templates."""

    def __init__(self, nsamp, sample_rate, sigma_t, cfg):
        self.nsamp, self.cfg = nsamp, cfg
        self.nfft = scipy.fft.next_fast_len(nsamp, real=True)
        self.freqs = scipy.fft.rfftfreq(self.nfft, 1.0 / sample_rate)
        self.weight = np.full(len(self.freqs), 2.0)
        self.weight[0] = 1.0
        if self.nfft % 2 == 0:
            self.weight[-1] = 1.0
        self.white_sel = ((self.freqs >= cfg.white_band[0])
                          & (self.freqs <= min(cfg.white_band[1], self.freqs[-1])))
        if not self.white_sel.any():
            raise ValueError(f"white_band {cfg.white_band} Hz is outside the spectrum "
                             f"(Nyquist {self.freqs[-1]:.1f} Hz)")
        self.templates = {s: gaussian_template_spectrum(self.nfft, sample_rate, s)
                          for s in np.unique(sigma_t)}

    def spectrum(self, x):
        """rfft of the rows of ``x``, their smoothed PSD and white level."""
        spec = scipy.fft.rfft(x, n=self.nfft, axis=1, workers=self.cfg.workers)
        psd = smoothed_psd((spec.real**2 + spec.imag**2).astype(np.float32),
                           self.cfg.bins_per_decade)
        return spec, psd, psd[:, self.white_sel].mean(axis=1).astype(float)

    def apply(self, spec, psd, white, sigma_t):
        """Filtered rows ``y`` and, per row, the amplitude normalization, Var(y) and knee."""
        cfg = self.cfg
        if cfg.highpass is None:
            fknee = fit_knee(self.freqs, psd, white, cfg.knee_bounds, cfg.white_band[0])
            fknee[np.isnan(fknee)] = cfg.knee_bounds[0]
        else:
            fknee = np.full(len(white), float(cfg.highpass))
        tmpl = np.stack([self.templates[s] for s in sigma_t])
        gain = butterworth_highpass(self.freqs, fknee, cfg.order) * tmpl / psd
        gain[:, 0] = 0.0
        norm = (self.weight * gain * tmpl).sum(axis=1) / self.nfft
        var_y = (self.weight * gain**2 * psd).sum(axis=1) / self.nfft**2
        y = scipy.fft.irfft(spec * gain, n=self.nfft, axis=1, workers=cfg.workers)[:, :self.nsamp]
        return y, norm, var_y, fknee


def _prepare(signal_rows, mask_rows, n_edge):
    x = np.array(signal_rows, dtype=np.float32)
    bad = ~np.isfinite(x)
    if mask_rows is not None:
        bad |= np.asarray(mask_rows, bool)
    x[bad] = 0.0
    _fill_bad(x, bad)
    _remove_edge_line(x, n_edge)
    return x, bad


def _refilter_bright(sp, x, spec, y, norm, var_y, psd, white, sigma_t, valid, sample_rate):
    """Second pass for rows holding a bright source: PSD re-estimated with it masked.

    A source much brighter than the noise dominates its detector's spectrum and would weight
    itself down; here samples with S/N above ``source_mask_snr`` (and 2 sigma_t around them) are
    interpolated over before the PSD is estimated again, and the original data refiltered.
    """
    cfg = sp.cfg
    snr0 = np.where(valid, np.abs(y) / np.sqrt(var_y)[:, None], 0.0)
    rows = np.flatnonzero(snr0.max(axis=1) > cfg.bright_snr)
    if not len(rows):
        return
    width = int(np.ceil(2 * np.max(sigma_t[rows]) * sample_rate))
    masked = ndimage.binary_dilation(snr0[rows] > cfg.source_mask_snr,
                                     structure=np.ones((1, 2 * width + 1), bool))
    xm = x[rows].copy()
    _fill_bad(xm, masked)
    _, psd_m, white_m = sp.spectrum(xm)
    y[rows], norm[rows], var_y[rows], _ = sp.apply(spec[rows], psd_m, white_m, sigma_t[rows])
    psd[rows], white[rows] = psd_m, white_m


def matched_filter(signal, sample_rate, sigma_t, cfg: FilterConfig = FilterConfig(),
                   mask=None) -> FilterResult:
    """Matched-filter every detector of ``signal`` (ndet, nsamps); see the module docstring.

    ``sigma_t``: template width in seconds, scalar or per detector. ``mask``: optional bool
    array (ndet, nsamps) of samples to ignore. The input array is not modified.
    """
    signal = np.asarray(signal)
    ndet, nsamp = signal.shape
    sigma_t = np.broadcast_to(np.asarray(sigma_t, dtype=float), (ndet,))
    if nsamp < 16:
        raise ValueError(f"only {nsamp} samples: too short to filter")
    sp = _Spectral(nsamp, sample_rate, sigma_t, cfg)
    out = FilterResult(
        snr=np.zeros((ndet, nsamp), np.float32), amplitude=np.zeros((ndet, nsamp), np.float32),
        valid=np.zeros((ndet, nsamp), bool), noise_level=np.zeros(ndet),
        fknee=np.zeros(ndet), sigma_amp=np.zeros(ndet), snr_scale=np.zeros(ndet),
        dead=np.zeros(ndet, bool), freqs=sp.freqs, nfft=sp.nfft)
    psds = []
    n_edge = max(1, min(nsamp // 4, int(round(sample_rate))))
    for start in range(0, ndet, cfg.chunk_dets):
        sl = slice(start, min(start + cfg.chunk_dets, ndet))
        x, bad = _prepare(signal[sl], None if mask is None else mask[sl], n_edge)
        spec, psd, white = sp.spectrum(x)
        dead = (white <= 0) | bad.all(axis=1)
        white[dead] = 1.0
        psd[dead] = 1.0
        y, norm, var_y, fknee = sp.apply(spec, psd, white, sigma_t[sl])
        valid = _valid_mask(bad, nsamp, sample_rate, cfg)
        valid[dead] = False
        if cfg.bright_snr is not None:
            _refilter_bright(sp, x, spec, y, norm, var_y, psd, white, sigma_t[sl], valid,
                             sample_rate)
        del x, spec
        psds.append(psd[~dead])
        sigma_y = np.sqrt(var_y)
        snr = (y / sigma_y[:, None]).astype(np.float32)
        measured = robust_std(snr, valid)
        scale = np.where(np.isfinite(measured) & (measured > 0), measured, 1.0)
        snr /= scale[:, None].astype(np.float32)
        snr[~valid] = 0.0
        amp = (y / norm[:, None]).astype(np.float32)
        amp[~valid] = 0.0
        out.snr[sl], out.amplitude[sl], out.valid[sl] = snr, amp, valid
        out.noise_level[sl] = np.where(dead, 0.0, np.sqrt(white / nsamp))
        out.fknee[sl] = fknee
        out.sigma_amp[sl] = np.where(dead, 0.0, sigma_y * scale / norm)
        out.snr_scale[sl] = np.where(dead, np.nan, scale)
        out.dead[sl] = dead
    out.median_psd = np.median(np.concatenate(psds), axis=0) if sum(map(len, psds)) else None
    return out


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
