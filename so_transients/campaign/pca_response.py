"""What the standard steps' PCA takes of an injected flare, for the fast injection path.

``transient_pca_filter`` subtracts ``R (R^T model)`` from the signal (:mod:`so_transients.
detect.pca`), where ``model`` is the PCA's model signal: a low-passed copy of the signal
(a ``transient_fourier_filter`` that wraps it), in which ``transient_pca_mask`` hid each
detector's brief excursions beyond ``limit`` (and ``buffer`` seconds around them). ``R`` is
fixed by the noise (a flare near the detection threshold changes the detectors' covariance by
about its S/N squared over the number of samples), so a flare ``s`` added to the TOD leaves
the step as

    s - R (R^T mask(lowpass(s)))

with ``mask`` zeroing each detector's samples of ``lowpass(s)`` beyond its limit. The flare's
own excursion decides the mask here, not the flare plus the noise as in the data: a detector
whose low-passed flare is within the noise of its limit may be masked in one and not in the
other. Without this the fast path missed the 2-10 % of a flare's flux the PCA takes and was
optimistic near the detection threshold (docs/results/table2.md, "Full site pipeline").

The noise-only group's run of the standard steps leaves ``R`` in ``aman.transient_pca_filter``
and the limits in ``aman.transient_pca_mask``; the low-pass is read from the standard steps'
config (:func:`model_signal_filter`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.fft

from so_transients.campaign.noise_model import fft_length
from so_transients.detect.spectral_ops import dilate_rows
from so_transients.preprocess.sotodlib_steps import TransientFourierFilter, sotodlib_name

#: seconds of zeros either side of a window before it is low-passed (a 4th-order Butterworth
#: at 3 Hz rings for well under a second)
LOWPASS_PAD = 5.0


def model_signal_filter(standard_steps):
    """``(pca_entry, lowpass_entry)``: the config entries of the standard steps' PCA and of
    the Fourier filter that makes its model signal (None when the PCA models the signal
    itself). ``(None, None)`` without a PCA step. Raises for sotodlib's own ``pca_filter``,
    which keeps no weights to model it with."""
    names = [sotodlib_name(step["name"]) for step in standard_steps]
    if "pca_filter" not in names:
        return None, None
    at = names.index("pca_filter")
    pca = standard_steps[at]
    if pca["name"] != "transient_pca_filter":
        raise ValueError(f"the fast injection path models transient_pca_filter, not "
                         f"{pca['name']} (it keeps no weights): use transient_pca_filter")
    model = pca.get("model_signal") or pca.get("signal", "signal")
    if model == pca.get("signal", "signal"):
        return pca, None
    for step in reversed(standard_steps[:at]):
        if sotodlib_name(step["name"]) == "fourier_filter" and step.get("wrap_name") == model:
            return pca, step
    raise ValueError(f"no fourier filter before {pca['name']} wraps its model signal {model!r}")


@dataclass
class PcaResponse:
    """The PCA step as a flare added to the TOD sees it (module doc)."""

    weights: np.ndarray        # (dets, n_modes): R
    limit: np.ndarray          # (dets,) the mask's limit in the model signal; inf: unmasked
    buffer: float              # s masked around an excursion
    lowpass: dict | None       # the config entry of the model signal's Fourier filter
    _chain: object = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def from_aman(cls, aman, lowpass):
        """From what the standard steps left in ``aman`` (None without a PCA step)."""
        if "transient_pca_filter" not in aman._fields:
            return None
        ndet = aman.dets.count
        if "transient_pca_mask" in aman._fields:
            mask = aman.transient_pca_mask
            limit, buffer = np.asarray(mask.limit, float), float(mask.buffer)
        else:
            limit, buffer = np.full(ndet, np.inf), 0.0
        return cls(np.asarray(aman.transient_pca_filter.weights, float), limit, buffer,
                   lowpass)

    def _lowpass_chain(self):
        """The model signal's filters as one sotodlib ``FilterChain``, built once."""
        if self._chain is None:
            self._chain = TransientFourierFilter(self.lowpass).filter_chain()
        return self._chain

    def model_signal(self, signal, sample_rate):
        """``signal`` (dets, m) low-passed as the model signal's filter does (a copy)."""
        if self.lowpass is None:
            return np.array(signal, np.float64)
        m = signal.shape[1]
        n = fft_length(m + 2 * int(np.ceil(LOWPASS_PAD * sample_rate)))
        spec = scipy.fft.rfft(signal, n=n, axis=1)
        freqs = scipy.fft.rfftfreq(n, 1.0 / sample_rate)
        self._lowpass_chain().apply(freqs, None, spec)
        return scipy.fft.irfft(spec, n=n, axis=1)[:, :m]

    def apply(self, signal, dets, sample_rate):
        """Subtract, in place, what the PCA takes of ``signal`` (rows: detectors ``dets``,
        the only ones it reaches)."""
        model = self.model_signal(signal, sample_rate)
        hidden = np.abs(model) > self.limit[dets][:, None]
        if hidden.any():
            grow = max(1, int(round(self.buffer * sample_rate)))
            model[dilate_rows(hidden, grow)] = 0.0
        weights = self.weights[dets]
        signal -= (weights @ (weights.T @ model)).astype(signal.dtype)
