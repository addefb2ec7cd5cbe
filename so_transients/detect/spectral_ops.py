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
def weight_spectrum(spec, base, base_index, inv_psd, edges, out):
    """``out[i, f] = spec[i, f] * base[base_index[i], f] / psd[i, bin(f)]``, DC set to zero
    (``out`` may be ``spec`` itself; else ``spec`` is kept for a second weighting)."""
    nrows, nbins = inv_psd.shape
    for i in range(nrows):
        b = base[base_index[i]]
        for f in range(edges[0]):
            out[i, f] = 0.0
        for k in range(nbins):
            w = inv_psd[i, k]
            for f in range(edges[k], edges[k + 1]):
                out[i, f] = spec[i, f] * (b[f] * w)


@njit(cache=True, nogil=True, fastmath=True)
def scale_rows(y, factor, n_edge, out, rows):
    """``out[rows[i]] = y[i, :nsamp] * factor[i]`` with ``n_edge`` samples zeroed at both
    ends; returns each row's largest ``|out|``."""
    nsamp = out.shape[1]
    nrows = len(rows)
    peak = np.zeros(nrows)
    n_edge = min(n_edge, nsamp // 2)
    for i in range(nrows):
        r = rows[i]
        f = factor[i]
        hi = np.float32(0.0)
        lo = np.float32(0.0)
        for s in range(n_edge):
            out[r, s] = 0.0
            out[r, nsamp - 1 - s] = 0.0
        for s in range(n_edge, nsamp - n_edge):
            v = y[i, s] * f
            out[r, s] = v
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
def _fill_run(x, i, start, end, nsamp):
    """Samples ``start .. end - 1`` of row ``i`` of ``x`` replaced by the line between their
    good neighbours (the nearest good value at the ends of the row's ``nsamp`` samples; zeros
    when there is none)."""
    left = x[i, start - 1] if start > 0 else (x[i, end] if end < nsamp else 0.0)
    right = x[i, end] if end < nsamp else left
    span = end - start + 1
    for j in range(start, end):
        frac = (j - start + 1) / span
        x[i, j] = left + (right - left) * frac


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
            _fill_run(x, i, start, s, nsamp)


@njit(cache=True, nogil=True)
def interpolate_above(x, snr, threshold, n):
    """In place, the samples of each row of ``x`` within ``n`` samples of one where
    ``|snr| > threshold`` replaced as :func:`interpolate_runs` replaces bad ones (the same as
    ``interpolate_runs(x, dilate_rows(abs(snr) > threshold, n))``, in one pass over ``snr``);
    returns the number of samples replaced per row."""
    nrows, nsamp = snr.shape
    counts = np.zeros(nrows, np.int64)
    for i in range(nrows):
        s = 0
        while s < nsamp:
            if not abs(snr[i, s]) > threshold:
                s += 1
                continue
            # a run of masked samples: from n before this one to n after the last sample
            # above the threshold that lies within it (runs that touch are one run)
            start = max(0, s - n)
            end = min(nsamp, s + n + 1)
            t = s + 1
            while t < min(nsamp, end + n + 1):
                if abs(snr[i, t]) > threshold:
                    end = min(nsamp, t + n + 1)
                t += 1
            counts[i] += end - start
            _fill_run(x, i, start, end, nsamp)
            s = end
    return counts


@njit(cache=True, nogil=True, fastmath=True)
def beam_normal_equations(along0, across0, y, w, params, geom, response, slope, alpha, beta):
    """chi^2 of the fit's beam model ``a0 B + c`` (see :mod:`so_transients.detect.fit`) in one pass,
    and the normal equations ``alpha = J^T W J`` (4, 4) and ``beta = J^T W r`` (4,) of the
    parameters ``(a0, dxi, deta, c)``, filled in place, without forming the Jacobian.

    ``params`` = (a0, dxi, deta, c); ``geom`` = (ux, uy, 1 / speed, lag0, 1 / dlag,
    1 / sigma^2): the drift direction, the uniform lags ``lag0 + k dlag`` on which
    ``response`` and its derivative ``slope`` are sampled (cubic Hermite interpolation, zero
    outside, as :func:`so_transients.detect.fit.response_spline`) and the beam width. Returns chi^2.
    """
    a0, dxi, deta, c = params[0], params[1], params[2], params[3]
    ux, uy, inv_speed, lag0, inv_dlag, inv_sigma2 = (geom[0], geom[1], geom[2], geom[3],
                                                      geom[4], geom[5])
    shift_along = dxi * ux + deta * uy
    shift_across = -dxi * uy + deta * ux
    m = len(response)
    dlag = 1.0 / inv_dlag
    # the 10 distinct entries of J^T W J and the 4 of J^T W r, as scalars the loop keeps in
    # registers; J = (shape, d/d dxi, d/d deta, 1)
    s00 = s01 = s02 = s03 = s11 = s12 = s13 = s22 = s23 = s33 = 0.0
    b0 = b1 = b2 = b3 = 0.0
    chi2 = 0.0
    for k in range(len(along0)):
        across = across0[k] - shift_across
        x = ((along0[k] - shift_along) * inv_speed - lag0) * inv_dlag
        r = 0.0
        s = 0.0
        if 0.0 <= x <= m - 1:
            # cubic Hermite interpolation on the response and its slope: r and s = dr/dtau
            i = min(int(x), m - 2)
            f = x - i
            f2 = f * f
            f3 = f2 * f
            r0, r1 = response[i], response[i + 1]
            t0, t1 = slope[i] * dlag, slope[i + 1] * dlag
            r = ((2 * f3 - 3 * f2 + 1) * r0 + (f3 - 2 * f2 + f) * t0
                 + (3 * f2 - 2 * f3) * r1 + (f3 - f2) * t1)
            s = ((6 * f2 - 6 * f) * (r0 - r1) + (3 * f2 - 4 * f + 1) * t0
                 + (3 * f2 - 2 * f) * t1) * inv_dlag
        g = np.exp(-0.5 * across * across * inv_sigma2)
        shape = r * g
        wk = w[k]
        resid = y[k] - a0 * shape - c
        chi2 += wk * resid * resid
        # d along / d(dxi, deta) = -(ux, uy); d across / d(dxi, deta) = (uy, -ux)
        d_resp = s * inv_speed * g
        d_gauss = shape * across * inv_sigma2
        j1 = a0 * (-ux * d_resp - uy * d_gauss)
        j2 = a0 * (-uy * d_resp + ux * d_gauss)
        ws, w1, w2 = wk * shape, wk * j1, wk * j2
        s00 += ws * shape
        s01 += ws * j1
        s02 += ws * j2
        s03 += ws
        s11 += w1 * j1
        s12 += w1 * j2
        s13 += w1
        s22 += w2 * j2
        s23 += w2
        s33 += wk
        b0 += ws * resid
        b1 += w1 * resid
        b2 += w2 * resid
        b3 += wk * resid
    alpha[0, 0], alpha[0, 1], alpha[0, 2], alpha[0, 3] = s00, s01, s02, s03
    alpha[1, 0], alpha[1, 1], alpha[1, 2], alpha[1, 3] = s01, s11, s12, s13
    alpha[2, 0], alpha[2, 1], alpha[2, 2], alpha[2, 3] = s02, s12, s22, s23
    alpha[3, 0], alpha[3, 1], alpha[3, 2], alpha[3, 3] = s03, s13, s23, s33
    beta[0], beta[1], beta[2], beta[3] = b0, b1, b2, b3
    return chi2


@njit(cache=True, nogil=True, fastmath=True)
def beam_amplitude_sums(track_xi, track_eta, det_xi, det_eta, amp, sigma_amp, reach, geom,
                        response, slope):
    """``(sum w y B, sum w B^2, n)`` of the unshifted beam ``B`` (as
    :func:`beam_normal_equations` models it, ``geom`` the same) over the samples of a fit
    window that can carry it: ``amp`` (ndet, nt) nonzero, ``sigma_amp`` (ndet,) positive
    (``w = sigma_amp^-2``) and no farther along the scan than ``reach`` (rad) from the
    track (``track_xi``, ``track_eta``: (nt,)). The amplitude fit of a null position in one
    pass, without the offsets, masks and model that a full fit builds."""
    ux, uy, inv_speed, lag0, inv_dlag, inv_sigma2 = (geom[0], geom[1], geom[2], geom[3],
                                                      geom[4], geom[5])
    m = len(response)
    dlag = 1.0 / inv_dlag
    wyb = wbb = 0.0
    n = 0
    for d in range(amp.shape[0]):
        sigma = sigma_amp[d]
        if not sigma > 0:
            continue
        wk = 1.0 / (sigma * sigma)
        for t in range(amp.shape[1]):
            y = float(amp[d, t])
            if y == 0.0:
                continue
            ox = det_xi[d] - track_xi[t]
            oy = det_eta[d] - track_eta[t]
            along = ox * ux + oy * uy
            if abs(along) > reach:
                continue
            across = -ox * uy + oy * ux
            n += 1
            x = (along * inv_speed - lag0) * inv_dlag
            if not 0.0 <= x <= m - 1:
                continue
            i = min(int(x), m - 2)
            f = x - i
            f2 = f * f
            f3 = f2 * f
            r = ((2 * f3 - 3 * f2 + 1) * response[i] + (f3 - 2 * f2 + f) * slope[i] * dlag
                 + (3 * f2 - 2 * f3) * response[i + 1] + (f3 - f2) * slope[i + 1] * dlag)
            shape = r * np.exp(-0.5 * across * across * inv_sigma2)
            wyb += wk * y * shape
            wbb += wk * shape * shape
    return wyb, wbb, n
