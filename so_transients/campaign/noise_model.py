"""Fast injection for recovery tests: the matched filter applied to an injected signal alone.

The matched filter is linear once its noise weighting is fixed. For injection-recovery
campaigns the noise-only observation is filtered once (:func:`so_transients.detect.matched_filter.
matched_filter`, which records each detector's binned PSD, knee and S/N factor in a
:class:`NoiseModel`); the S/N of an injected source is then the noise-only S/N plus the filtered
injection, and the injection is short: a source crossing touches a detector for a fraction of a
second, so it is filtered over a window of a few seconds around the crossing instead of the
whole observation.

The filter's impulse response depends only on the frequency response
``H(f) = B_hp(f) T(f) / P(f)``, so filtering a window of ``m`` samples with ``H`` sampled on
that window's frequency grid gives the same output as the full-length filter, as long as the
window is longer than the impulse response (about ``1 / f_hp``; windows are padded by
``pad`` seconds, 10 by default). The template spectrum is the analytic transform of the
sampled Gaussian, exact for templates wider than a sample.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.fft

from so_transients.detect.matched_filter import FilterResult, butterworth_highpass
from so_transients.common.scan_geometry import sample_rate


@dataclass
class NoiseModel:
    """Per-detector weighting of a filtered noise-only observation."""

    sample_rate: float
    nfft: int                    # FFT length of the full observation (sets the PSD units)
    edges: np.ndarray            # rfft indices (of the full FFT) bounding the PSD bins
    psd_bins: np.ndarray         # (ndet, nbins)
    fknee: np.ndarray            # (ndet,) high-pass frequency
    sigma_t: np.ndarray          # (ndet,) template width, s
    snr_factor: np.ndarray       # (ndet,) S/N per unit filter output
    #: (ndet,) the effective number of frequencies each detector's filter used, as the
    #: filter computed it (``FilterResult.n_eff``; NaN for dead detectors)
    n_eff: np.ndarray
    order: int = 4
    #: rows whose own source would bias their PSD by more than this (S/N^2 / n_eff) are
    #: filtered again with a PSD estimated without it (the filter's ``bright_bias``)
    bright_bias: float = np.inf
    _responses: dict = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_filter(cls, result: FilterResult, sample_rate, sigma_t, order=4,
                    bright_bias=None):
        ndet = len(result.snr_factor)
        return cls(float(sample_rate), int(result.nfft), np.asarray(result.psd_edges),
                   np.asarray(result.psd_bins, float), np.asarray(result.fknee, float),
                   np.broadcast_to(np.asarray(sigma_t, float), (ndet,)).copy(),
                   np.asarray(result.snr_factor, float), np.asarray(result.n_eff, float), order,
                   np.inf if bright_bias is None else float(bright_bias))

    @classmethod
    def from_aman(cls, aman):
        """The noise model ``transient_filter`` left in ``aman.transient_filter``."""
        summary = aman.transient_filter
        missing = [k for k in ("psd_bins", "n_eff") if k not in summary._fields]
        if missing:
            raise ValueError(f"aman.transient_filter holds no noise model ({', '.join(missing)}):"
                             " run transient_filter's process() on this aman first")
        return cls(sample_rate(aman.timestamps, "NoiseModel:"), int(summary.nfft),
                   np.asarray(summary.psd_edges), np.asarray(summary.psd_bins, float),
                   np.asarray(summary.fknee, float), np.asarray(summary.sigma_t, float),
                   np.asarray(summary.snr_factor, float), np.asarray(summary.n_eff, float),
                   int(summary.order),
                   float(summary.bright_bias) if "bright_bias" in summary._fields else np.inf)

    def _bins(self, freqs):
        """The PSD bin of each frequency (Hz)."""
        index = np.rint(freqs * self.nfft / self.sample_rate).astype(int)
        return np.clip(np.searchsorted(self.edges, index, side="right") - 1,
                       0, self.psd_bins.shape[1] - 1)

    def _template(self, dets, freqs):
        sigma = self.sigma_t[dets][:, None]
        return (self.sample_rate * sigma * np.sqrt(2 * np.pi)
                * np.exp(-2 * (np.pi * freqs[None, :] * sigma) ** 2))

    def gain(self, dets, freqs):
        """Filter response (dets, nf) at ``freqs`` (Hz): high-pass x template / PSD."""
        hp = butterworth_highpass(freqs, self.fknee[dets], self.order)
        psd = self.psd_bins[dets][:, self._bins(freqs)]
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.where(psd > 0, hp * self._template(dets, freqs) / psd, 0.0)   # dead: 0
        out[:, freqs == 0] = 0.0
        return out

    def own_psd_loss(self, freqs):
        """The share of a source's filtered signal, per frequency (Hz), that a PSD estimated
        from data holding it takes back on average: each bin's PSD is the mean of its ``m``
        frequencies' power, whose cross term with the noise, ``2 Re(N S*) / m``, is linear in
        the source, and weighting by its inverse takes ``1/m`` of each of its frequencies'
        response (1.7 % of a crossing's S/N in 4 minutes of f090 data; less in longer data,
        whose bins hold more frequencies)."""
        counts = np.diff(self.edges).astype(float)
        return 1.0 / counts[self._bins(freqs)]

    def snr_response(self, n, own_psd=True):
        """S/N per unit input in Fourier space, (ndet, n // 2 + 1), for real FFTs of length
        ``n``: the gain times each detector's S/N factor, less with ``own_psd`` what the PSD
        estimated from data holding the source takes (:meth:`own_psd_loss`). Cached."""
        key = (n, bool(own_psd))
        if key not in self._responses:
            freqs = scipy.fft.rfftfreq(n, 1.0 / self.sample_rate)
            every = np.arange(len(self.fknee))
            response = self.gain(every, freqs) * self.snr_factor[:, None]
            if own_psd:
                response *= 1.0 - self.own_psd_loss(freqs)
            self._responses[key] = response.astype(np.float32)
        return self._responses[key]


def fft_length(n):
    """The smallest 2^k or 3 x 2^k that is >= ``n`` (both fast for FFTs)."""
    power = 1 << max(int(np.ceil(np.log2(max(n, 1)))), 0)
    return min(power, 3 * power // 4) if 3 * power // 4 >= n else power


def filtered_snr(model: NoiseModel, dets, signal, pad=10.0):
    """S/N timestream (len(dets), m) that the noise model's filter makes of ``signal``
    (len(dets), m), a window of injected signal only, zero-padded by at least ``pad`` seconds
    on each side (FFT lengths are 2^k or 3 x 2^k, so that few responses need computing).

    As the filter weighs it: with each detector's PSD estimated from the data holding the
    signal (:meth:`NoiseModel.own_psd_loss`), except on detectors where the signal is bright
    enough (its S/N^2 / n_eff above ``bright_bias``) for the filter's second pass, whose PSD
    leaves the source out."""
    signal = np.asarray(signal, np.float32)
    dets = np.asarray(dets, int)
    m = signal.shape[1]
    n = fft_length(m + 2 * int(np.ceil(pad * model.sample_rate)))
    spec = scipy.fft.rfft(signal, n=n, axis=1)
    out = scipy.fft.irfft(spec * model.snr_response(n)[dets], n=n, axis=1)[:, :m]
    if np.isfinite(model.bright_bias) and len(dets):
        peak = np.abs(out).max(axis=1)
        bright = np.flatnonzero(peak**2 / model.n_eff[dets] > model.bright_bias)
        if len(bright):
            again = spec[bright] * model.snr_response(n, own_psd=False)[dets[bright]]
            out[bright] = scipy.fft.irfft(again, n=n, axis=1)[:, :m]
    return out
