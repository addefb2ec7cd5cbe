"""sotodlib's PCA filter (``tod_ops.pca``: ``get_pca``, ``get_pca_model``, ``add_model``) in
blocks of samples: the same modes and the same cleaned signal, without its full copies.

sotodlib's ``pca_filter`` step computes the detectors' covariance with ``np.cov`` (a float64,
mean-subtracted copy of the whole model signal), the modes as ``R^T model`` (another float64
copy of it) and subtracts them detector by detector. For one hour of an f090 wafer-band
(2.7 GB of float32 signal) the copies are 5.4 GB each and make the site pipeline's peak
memory; the covariance's float64 products are most of its time. Here the covariance is summed
over blocks of ``block`` samples (each block's products in float32 and accumulated in
float64: 1e-7 of the covariance), and the modes are found and subtracted block by block, so
nothing larger than a block is made.

Detectors whose model signal is not finite everywhere are left out of the covariance and the
modes and are not cleaned (sotodlib's ``np.cov`` spreads one NaN to every detector): the
caller says which and why.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from so_transients.common.step_config import positive, setting


@dataclass
class PcaConfig:
    """Settings of the ``transient_pca_filter`` step (:func:`pca_filter`)."""

    n_modes: int = setting(10, "", "strongest principal components subtracted (sotodlib's n_modes)")
    block: int = setting(8192, "", "samples per block of the covariance and the subtraction")

    def __post_init__(self):
        positive("transient_pca_filter", n_modes=self.n_modes, block=self.block)


def covariance(model, rows, block):
    """The covariance (float64, ``np.cov``'s normalization) of the rows ``rows`` of
    ``model`` (dets, samps), summed over blocks of ``block`` samples."""
    nsamp = model.shape[1]
    mean = np.array([model[r].mean(dtype=np.float64) for r in rows])
    cov = np.zeros((len(rows), len(rows)))
    buffer = np.empty((len(rows), min(block, nsamp)), np.float32)
    for start in range(0, nsamp, block):
        part = buffer[:, :min(block, nsamp - start)]
        np.take(model[:, start:start + block], rows, axis=0, out=part, mode="clip")
        part -= mean[:, None].astype(np.float32)
        cov += part @ part.T
    return cov / max(nsamp - 1, 1)


@dataclass
class PcaModes:
    """What :func:`pca_filter` subtracted: ``weights`` (dets, n_modes) is ``R``, each
    detector's weight on the modes (zero for the detectors ``left_out``), so that a signal
    added to the data before the step loses ``R (R^T model)`` of it, where ``model`` is its
    part of the model signal (:mod:`so_transients.campaign.pca_response`)."""

    left_out: np.ndarray      # (dets,) bool: model not finite everywhere, not cleaned
    weights: np.ndarray       # (dets, n_modes) float64


def pca_filter(signal, model, n_modes, block=8192) -> PcaModes:
    """Subtract from ``signal`` (dets, samps; in place) its share of the ``n_modes`` strongest
    principal components of ``model`` (the same shape; ``signal`` itself, or a low-passed
    copy), as sotodlib's ``pca_filter`` step does: ``signal -= R (R^T model)`` with ``R`` the
    covariance's leading eigenvectors. Returns ``R`` and the detectors left out: those whose
    model is not finite everywhere."""
    ndet, nsamp = model.shape
    left_out = ~np.isfinite(model).all(axis=1)
    rows = np.flatnonzero(~left_out)
    if len(rows) < n_modes:
        raise ValueError(f"{len(rows)} detectors with a finite model signal, fewer than the "
                         f"{n_modes} PCA modes")
    eigval, eigvec = np.linalg.eigh(covariance(model, rows, block))
    eigval[np.isnan(eigval)] = 0.0
    lead = eigvec[:, np.argsort(-eigval)[:n_modes]]          # (rows, n_modes), float64
    lead_t = np.ascontiguousarray(lead.T)
    part = np.empty((len(rows), min(block, nsamp)), np.float32)
    for start in range(0, nsamp, block):
        stop = min(start + block, nsamp)
        rows_model = part[:, :stop - start]
        np.take(model[:, start:stop], rows, axis=0, out=rows_model)
        modes = lead_t @ rows_model.astype(np.float64)         # (n_modes, block), as sotodlib
        if len(rows) == ndet:
            signal[:, start:stop] -= lead @ modes
        else:
            signal[rows, start:stop] -= lead @ modes
    weights = np.zeros((ndet, n_modes))
    weights[rows] = lead
    return PcaModes(left_out, weights)
