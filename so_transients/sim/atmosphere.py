"""Atmosphere as a frozen 2-D turbulent screen, advected by wind, seen along every line of sight.

Model (Church 1995; Errard et al. 2015, simplified to one thin layer):

* a Gaussian random field on a horizontal layer at ``altitude`` with the von Karman form of the
  Kolmogorov spectrum, ``P(kappa) ~ (kappa^2 + kappa_0^2)^(-11/6)`` in angular wavenumber
  ``kappa = 2 pi k``, with ``kappa_0 = 1 / L0`` for the outer scale ``L0``;
* averaged over the telescope's near-field beam, a cylinder as wide as the 6 m primary
  (``aperture``; modelled as the Gaussian with the same second moment as a uniform disk,
  sigma = D/4), which is what makes neighbouring detectors see nearly the same atmosphere;
* frozen and carried by the wind: a detector pointing at (az, el) at time t sees the layer at
  ``R (sin az, cos az) - wind * t`` with ``R = altitude / tan(el)`` (x east, y north).

Amplitude (the documented scaling). In point-source-calibrated mJy the atmosphere is scaled per
band so that the detector PSD of atmosphere alone equals the band's white-noise PSD at the band's
knee frequency: ``P_atm(f_knee) = P_white = 2 sigma_w^2 / f_samp``. The default knee is the
paper's measured 1.23 Hz at f090, used for every band (the paper gives no other band's knee); set
``atmosphere.fknee`` per band to change it. The screen is one physical realization shared by both
bands of every wafer and by all tubes observing at the same time, so bands and tubes see
correlated atmosphere, as in real data.
"""
from __future__ import annotations

import numpy as np
import scipy.fft
from numba import njit
from scipy import signal as sps


def _von_karman_filter(ny, nx, pixel, outer_scale, aperture):
    ky = scipy.fft.fftfreq(ny, d=pixel)[:, None]
    kx = scipy.fft.rfftfreq(nx, d=pixel)[None, :]
    k2 = kx**2 + ky**2
    sigma_ap = aperture / 4.0   # Gaussian with the second moment of a uniform disk of diameter D
    amp = (k2 + (2 * np.pi * outer_scale) ** -2) ** (-11.0 / 12.0) * np.exp(-2 * np.pi**2 * k2 * sigma_ap**2)
    amp[0, 0] = 0.0
    return amp


class AtmosphereScreen:
    """A realization of the turbulent layer covering the box ``[x0, x1] x [y0, y1]`` (metres).

    Unit normalization: the field has unit variance; :meth:`calibrate` gives per-band scalings.
    """

    def __init__(self, config, bounds, rng: np.random.Generator):
        self.config = config
        x0, x1, y0, y1 = bounds
        pix = config.pixel
        self.nx = scipy.fft.next_fast_len(int(np.ceil((x1 - x0) / pix)) + 8, real=True)
        self.ny = scipy.fft.next_fast_len(int(np.ceil((y1 - y0) / pix)) + 8, real=True)
        self.x0, self.y0 = x0 - 4 * pix, y0 - 4 * pix
        white = rng.standard_normal((self.ny, self.nx), dtype=np.float32)
        spec = scipy.fft.rfft2(white, workers=-1)
        del white
        spec *= _von_karman_filter(self.ny, self.nx, pix, config.outer_scale, config.aperture)
        field = scipy.fft.irfft2(spec, s=(self.ny, self.nx), workers=-1)
        del spec
        field /= field.std()
        self.field = field.astype(np.float32)

    @property
    def wind(self):
        angle = np.radians(self.config.wind_direction)
        return self.config.wind_speed * np.cos(angle), self.config.wind_speed * np.sin(angle)

    def sample(self, t_rel, az, daz, el_det):
        """Screen value seen by detectors along their lines of sight, shape (ndet, nsamps).

        ``t_rel``: seconds since the screen's epoch; ``az``: boresight azimuth per sample
        (radians); ``daz``, ``el_det``: each detector's azimuth offset and elevation (radians).
        """
        t_rel = np.asarray(t_rel, dtype=np.float64)
        az = np.asarray(az, dtype=np.float64)
        daz = np.atleast_1d(np.asarray(daz, dtype=np.float64))
        el_det = np.atleast_1d(np.asarray(el_det, dtype=np.float64))
        wx, wy = self.wind
        out = np.empty((len(daz), len(t_rel)), dtype=np.float32)
        _sample_screen(self.field, (self.x0, self.y0, self.config.pixel), wx, wy,
                       self.config.altitude / np.tan(el_det), np.sin(daz), np.cos(daz),
                       t_rel, np.sin(az), np.cos(az), out)
        return out


@njit(cache=True, nogil=True)
def _sample_screen(field, origin, wx, wy, reach, sin_daz, cos_daz, t_rel, sin_az, cos_az, out):
    """Bilinear interpolation of ``field`` at every detector's line of sight, as
    ``ndimage.map_coordinates(order=1, mode="nearest")`` would (coordinates beyond the edge
    take the edge values), in one pass without coordinate arrays."""
    x0, y0, pix = origin
    ny, nx = field.shape
    for d in range(out.shape[0]):
        for k in range(out.shape[1]):
            # sin(az + daz), cos(az + daz) from the per-sample and per-detector parts
            sin_t = sin_az[k] * cos_daz[d] + cos_az[k] * sin_daz[d]
            cos_t = cos_az[k] * cos_daz[d] - sin_az[k] * sin_daz[d]
            col = (reach[d] * sin_t - wx * t_rel[k] - x0) / pix
            row = (reach[d] * cos_t - wy * t_rel[k] - y0) / pix
            col = min(max(col, 0.0), nx - 1.0)
            row = min(max(row, 0.0), ny - 1.0)
            i, j = min(int(row), ny - 2), min(int(col), nx - 2)
            fr, fc = row - i, col - j
            out[d, k] = ((1 - fr) * ((1 - fc) * field[i, j] + fc * field[i, j + 1])
                         + fr * ((1 - fc) * field[i + 1, j] + fc * field[i + 1, j + 1]))


def screen_bounds(config, t_rel, az, el_min, el_max, margin=100.0):
    """Box (x0, x1, y0, y1) in metres that every line of sight crosses during ``t_rel``."""
    wx = config.wind_speed * np.cos(np.radians(config.wind_direction))
    wy = config.wind_speed * np.sin(np.radians(config.wind_direction))
    xs, ys = [], []
    for el in (el_min, el_max):
        reach = config.altitude / np.tan(el)
        xs.append(reach * np.sin(az) - wx * t_rel)
        ys.append(reach * np.cos(az) - wy * t_rel)
    pad = margin + 3 * config.aperture
    return (min(map(np.min, xs)) - pad, max(map(np.max, xs)) + pad,
            min(map(np.min, ys)) - pad, max(map(np.max, ys)) + pad)


def unit_psd_at(screen, t_rel, az, el, sample_rate, freq):
    """PSD (per Hz, one-sided) of the unit screen seen from the boresight, at frequency ``freq``.

    Welch-averaged, then a power law fitted between freq/2.5 and 2.5 freq so that one noisy
    bin does not set the calibration.
    """
    tod = screen.sample(t_rel, az, np.zeros(1), np.array([el]))[0].astype(np.float64)
    nper = int(min(len(tod), 2 ** np.ceil(np.log2(20 * sample_rate / freq))))
    f, p = sps.welch(tod, fs=sample_rate, nperseg=nper)
    sel = (f >= freq / 2.5) & (f <= freq * 2.5)
    if sel.sum() < 3:
        raise ValueError(f"observation too short to calibrate the atmosphere at {freq} Hz")
    slope, offset = np.polyfit(np.log(f[sel]), np.log(p[sel]), 1)
    return float(np.exp(offset + slope * np.log(freq)))


def band_amplitude(unit_psd, white_mjy, sample_rate):
    """Scale (mJy per unit screen) making the atmosphere PSD equal the white PSD at the knee."""
    white_psd = 2.0 * white_mjy**2 / sample_rate
    return float(np.sqrt(white_psd / unit_psd))
