"""Properties of the SO LAT frequency bands used by the simulator and the detection steps.

Beam widths come from sotodlib's nominal hardware model (``sim_hardware.sim_nominal()``, telescope
``LAT``, keys ``LAT_f090`` ... ``LAT_f290``); white-noise levels and sample rates are those of the
reference paper (Clancy et al. 2025, sections 2.2 and 5.2). Band names follow SO's ``det_info``
convention (``f090``, ``f150``, ``f220``, ``f280``); sotodlib's hardware model calls the two UHF
bands ``LAT_f230`` and ``LAT_f290``.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from so_transients.common.angles import ARCMIN


#: det_info bandpass name -> key in sotodlib's nominal hardware model.
HARDWARE_BAND_KEY = {"f090": "LAT_f090", "f150": "LAT_f150", "f220": "LAT_f230", "f280": "LAT_f290"}

#: Per-sample white noise in point-source-calibrated mJy (paper, section 5.2).
WHITE_NOISE_MJY = {"f090": 367.0, "f150": 353.0, "f220": 520.0, "f280": 988.0}

#: Band centre frequencies (GHz) of the reference paper (its Table 1): spectral indices use
#: these; lightcurvedb's integer ``frequency`` uses the band's name (90, 150, 220, 280).
CENTER_GHZ = {"f090": 93.0, "f150": 145.0, "f220": 225.0, "f280": 280.0}

#: The atmospheric knee the paper measured at f090 (Hz): the matched filter's default
#: high-pass and the simulated atmosphere's knee in every band.
PAPER_KNEE_HZ = 1.23

#: Wafer flavour -> (bands, sample rate in Hz) (paper, section 2.2).
FLAVOR_BANDS = {"LAT_MF": ("f090", "f150"), "LAT_UHF": ("f220", "f280")}
FLAVOR_SAMPLE_RATE = {"LAT_MF": 220.0, "LAT_UHF": 340.0}


def fwhm_to_sigma(fwhm):
    """Gaussian sigma for a FWHM: FWHM / (2 sqrt(2 ln 2))."""
    return fwhm / (2.0 * np.sqrt(2.0 * np.log(2.0)))


def sigma_fwhm_by_band(beam_sigma, bands) -> dict:
    """The paper's clustering scale sigma_FWHM = FWHM / (2 sqrt(ln 2)) = sqrt(2) x the beam
    sigma, per band, from each detector's beam sigma (radians)."""
    beam_sigma, bands = np.asarray(beam_sigma), np.asarray(bands)
    return {b: float(np.sqrt(2) * np.median(beam_sigma[bands == b])) for b in np.unique(bands)}


@dataclass(frozen=True)
class Band:
    """One observing band: name, beam FWHM (radians) and white noise per sample (mJy)."""

    name: str
    fwhm: float
    white_noise_mjy: float

    @property
    def sigma(self) -> float:
        """Gaussian beam sigma in radians."""
        return fwhm_to_sigma(self.fwhm)


@lru_cache(maxsize=1)
def nominal_hardware():
    """sotodlib's nominal hardware model (cached: building it takes a moment)."""
    from sotodlib import sim_hardware

    return sim_hardware.sim_nominal()


def get_band(name: str) -> Band:
    """Return the :class:`Band` called ``name`` (``f090``, ``f150``, ``f220`` or ``f280``)."""
    if name not in HARDWARE_BAND_KEY:
        raise ValueError(f"unknown band {name!r}; expected one of {sorted(HARDWARE_BAND_KEY)}")
    fwhm_arcmin = nominal_hardware().data["telescopes"]["LAT"]["fwhm"][HARDWARE_BAND_KEY[name]]
    return Band(name=name, fwhm=float(fwhm_arcmin) * ARCMIN, white_noise_mjy=WHITE_NOISE_MJY[name])


def nominal_fwhm_arcmin() -> dict:
    """Nominal beam FWHM (arcmin) of every band, from sotodlib's hardware model."""
    return {name: get_band(name).fwhm / ARCMIN for name in HARDWARE_BAND_KEY}
