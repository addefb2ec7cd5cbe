"""CMB temperature anisotropies: a pixell realization sampled at every detector's pointing.

The realization is drawn on a CAR patch covering the observation's footprint from the fiducial
lensed TT spectrum that healpy ships (``healpy/data/totcls.dat``, D_ell in uK^2), smoothed by the
band's Gaussian beam and converted to point-source-calibrated mJy:
``S = dB/dT(nu) x 2 pi sigma_beam^2 x dT``. Sampling uses so3g's map-to-TOD projection
(bilinear interpolation), which never stores per-sample pointing.
"""
from __future__ import annotations

import importlib.resources

import numpy as np
from pixell import enmap, utils
from so3g.proj import Assembly, FocalPlane, Projectionist

from so_transients.common.bands import HARDWARE_BAND_KEY, nominal_hardware



def fiducial_cl():
    """C_ell (uK^2) of the fiducial TT spectrum, from ell = 0."""
    path = importlib.resources.files("healpy") / "data" / "totcls.dat"
    data = np.loadtxt(str(path))
    ell, dl = data[:, 0], data[:, 1]
    cl = np.zeros_like(dl)
    cl[2:] = dl[2:] * 2 * np.pi / (ell[2:] * (ell[2:] + 1))
    return cl


def mjy_per_uk(band) -> float:
    """Point-source-calibrated mJy per uK_CMB for a Gaussian beam at the band's centre frequency."""
    centre_ghz = nominal_hardware().data["bands"][HARDWARE_BAND_KEY[band.name]]["center"]
    jy_per_sr_per_k = utils.dplanck(centre_ghz * 1e9)
    return float(jy_per_sr_per_k * 2 * np.pi * band.sigma**2 * 1e-6 * 1e3)


def footprint_geometry(ra, dec, pad, resolution):
    """CAR geometry covering RA/Dec samples (radians) plus ``pad`` radians on every side."""
    ra_ref = np.median(ra)
    ra_unwrapped = ra_ref + np.angle(np.exp(1j * (ra - ra_ref)))
    box = np.array([[dec.min() - pad, ra_unwrapped.max() + pad],
                    [dec.max() + pad, ra_unwrapped.min() - pad]])
    return enmap.geometry(pos=box, res=resolution, proj="car")


class CmbSky:
    """One CMB realization on a patch, beam-smoothed per band on demand."""

    def __init__(self, shape, wcs, rng: np.random.Generator):
        seed = int(rng.integers(2**31 - 1))
        self.map_uk = enmap.rand_map(shape, wcs, fiducial_cl()[None, None], seed=seed)
        self._band_maps = {}

    def band_map(self, band):
        """The realization smoothed by the band's beam, in mJy, shape (1, ny, nx)."""
        if band.name not in self._band_maps:
            smooth = enmap.smooth_gauss(self.map_uk, band.sigma) * mjy_per_uk(band)
            self._band_maps[band.name] = enmap.enmap(smooth[None].astype(np.float64), smooth.wcs)
        return self._band_maps[band.name]

    def sample(self, band, sight, xi, eta, gamma):
        """CMB signal (float32, shape (ndet, nsamps)) seen by detectors along boresight ``sight``."""
        sky = self.band_map(band)
        proj = Projectionist.for_geom(sky.shape, sky.wcs, interpol="bilinear")
        fp = FocalPlane.from_xieta(xi, eta, gamma)
        out = np.zeros((len(xi), len(np.asarray(sight.Q))), dtype=np.float32)
        proj.from_map(sky, Assembly.attach(sight, fp), signal=out, comps="T")
        return out
