"""Fused loops of the matched filter, compiled with numba: one pass over the data per operation.

The matched filter's cost should be its two FFTs. Everything else it does per sample (removing
the edge line, the binned power spectrum, the spectral weighting, the S/N normalization and the
search for each row's peak) is done here in single passes over arrays already in cache, without
the temporaries that the same numpy expressions would allocate. The functions release the GIL,
so chunks of detectors can be filtered in parallel threads.

Conventions: ``spec`` is the rfft of a chunk of rows (complex64, (nrows, nf)); ``edges`` are the
bin edges of the log-spaced PSD bins over frequencies ``edges[0] = 1 .. edges[-1] = nf`` (DC is
not in a bin and is always zeroed by the weighting).
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, fastmath=True)
def remove_line_and_bin(spec, line_a, line_c, f_ones, f_ramp, edges, out):
    """In place, ``spec -= a F_ones + c F_ramp`` per row (a line in the time domain), and the
    mean power ``|spec|^2`` of each row in each bin into ``out`` (nrows, nbins).

    ``spec`` is passed as its float32 view (nrows, 2 nf) and ``f_ones``/``f_ramp`` likewise
    (2 nf,), so that the loop runs in single precision."""
    nrows, nbins = out.shape
    for i in range(nrows):
        a = np.float32(line_a[i])
        c = np.float32(line_c[i])
        for k in range(nbins):
            total = np.float32(0.0)
            for j in range(2 * edges[k], 2 * edges[k + 1]):
                z = spec[i, j] - a * f_ones[j] - c * f_ramp[j]
                spec[i, j] = z
                total += z * z
            out[i, k] = total / (edges[k + 1] - edges[k])


@njit(cache=True, nogil=True)
def weight_spectrum(spec, base, base_index, inv_psd, edges):
    """In place, ``spec[i, f] *= base[base_index[i], f] / psd[i, bin(f)]``; DC set to zero."""
    nrows, nbins = inv_psd.shape
    for i in range(nrows):
        b = base[base_index[i]]
        for f in range(edges[0]):
            spec[i, f] = 0.0
        for k in range(nbins):
            w = inv_psd[i, k]
            for f in range(edges[k], edges[k + 1]):
                spec[i, f] = spec[i, f] * (b[f] * w)


@njit(cache=True, nogil=True, fastmath=True)
def scale_rows(y, factor, n_edge, out):
    """``out[i] = y[i, :nsamp] * factor[i]`` with ``n_edge`` samples zeroed at both ends;
    returns each row's largest ``|out|``."""
    nrows, nsamp = out.shape
    peak = np.zeros(nrows)
    n_edge = min(n_edge, nsamp // 2)
    for i in range(nrows):
        f = factor[i]
        hi = np.float32(0.0)
        lo = np.float32(0.0)
        for s in range(n_edge):
            out[i, s] = 0.0
            out[i, nsamp - 1 - s] = 0.0
        for s in range(n_edge, nsamp - n_edge):
            v = y[i, s] * f
            out[i, s] = v
            hi = max(hi, v)
            lo = min(lo, v)
        peak[i] = max(hi, -lo)
    return peak


@njit(cache=True, nogil=True)
def dilate_rows(mask, n):
    """``mask`` (rows, nsamp) widened by ``n`` samples on each side, in one pass each way."""
    nrows, nsamp = mask.shape
    out = np.zeros_like(mask)
    for i in range(nrows):
        last = -n - 1
        for s in range(nsamp):
            if mask[i, s]:
                last = s
            if s - last <= n:
                out[i, s] = True
        last = nsamp + n + 1
        for s in range(nsamp - 1, -1, -1):
            if mask[i, s]:
                last = s
            if last - s <= n:
                out[i, s] = True
    return out


@njit(cache=True, nogil=True)
def interpolate_runs(x, bad):
    """In place, each run of ``bad`` samples replaced by the line between its good neighbours
    (the nearest good value at the ends; zeros for a row with no good sample)."""
    nrows, nsamp = bad.shape
    for i in range(nrows):
        s = 0
        while s < nsamp:
            if not bad[i, s]:
                s += 1
                continue
            start = s
            while s < nsamp and bad[i, s]:
                s += 1
            left = x[i, start - 1] if start > 0 else (x[i, s] if s < nsamp else 0.0)
            right = x[i, s] if s < nsamp else left
            span = s - start + 1
            for j in range(start, s):
                frac = (j - start + 1) / span
                x[i, j] = left + (right - left) * frac


@njit(cache=True, nogil=True, fastmath=True)
def beam_terms(along0, across0, shift_along, shift_across, inv_speed, lag0, inv_dlag, response,
               slope, inv_sigma2, shape, d_resp, d_gauss):
    """The fit's beam model at every sample in one pass (see :mod:`so_transients.fit`).

    ``response``/``slope`` are sampled on uniform lags ``lag0 + k / inv_dlag`` and linearly
    interpolated (zero outside, as ``np.interp(..., left=0, right=0)``). Fills ``shape`` =
    response(tau) x gauss(across) and, when ``d_resp`` is non-empty, the derivative terms
    ``d_resp`` = slope(tau) / speed x gauss and ``d_gauss`` = shape x across / sigma^2.
    """
    m = len(response)
    jac = len(d_resp) > 0
    for k in range(len(along0)):
        across = across0[k] - shift_across
        x = ((along0[k] - shift_along) * inv_speed - lag0) * inv_dlag
        r = 0.0
        s = 0.0
        if 0.0 <= x <= m - 1:
            i = min(int(x), m - 2)
            f = x - i
            r = response[i] + f * (response[i + 1] - response[i])
            s = slope[i] + f * (slope[i + 1] - slope[i])
        g = np.exp(-0.5 * across * across * inv_sigma2)
        shape[k] = r * g
        if jac:
            d_resp[k] = s * inv_speed * g
            d_gauss[k] = r * g * across * inv_sigma2
