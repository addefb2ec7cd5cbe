"""The instrument's imperfections: what makes real detectors differ from the ideal ones.

Per-detector properties are drawn once per tube (:func:`draw_flaws`) and then hold in every
observation, as for a real array:

* yield: a fraction of each wafer-band's detectors is dead (records zeros, NaN or a constant,
  with or without a small readout noise, and still the readout's jumps and the cosmic rays)
  and another fraction is noisy (noise a factor above the rest); a few channels, drawn
  independently, are lost (NaN throughout);
* noise: each detector's white-noise level scatters (log-normal) and it can have its own 1/f
  noise with its own knee, on top of the common atmosphere;
* calibration: the detector's response to the sky differs from what the metadata say;
* time constant: the detector sees the sky through a one-pole low-pass 1/(1 + 2 pi i f tau),
  and det_cal's ``tau_eff`` states it with an error (and as NaN for some detectors);
* focal plane: the metadata xi, eta differ from the true ones (the TOD uses the true ones).

Per-observation readout jumps live in :mod:`so_transients.sim.jumps`. All draws come from
generators keyed by (seed, component, tube, wafer, band), so the same seed gives the same
detectors whatever is simulated alongside them; each option off draws nothing and changes nothing.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from astropy import units as u
from astropy.table import Table
from scipy import fft

from so_transients.common.angles import ARCSEC

OK, DEAD, NOISY, LOST = "ok", "dead", "noisy", "lost"


@dataclass
class DetectorFlaws:
    """Imperfections of a set of detectors (arrays in the order of their ``readout_id``)."""

    status: np.ndarray          # OK, DEAD, NOISY or LOST
    noise_factor: np.ndarray    # white (and 1/f) noise level over the band's nominal level
    fknee: np.ndarray           # Hz, knee of the detector's own 1/f noise; 0: none
    gain: np.ndarray            # true sky response over the metadata's (1: perfect calibration)
    tau: np.ndarray             # s, time constant; 0: instantaneous
    tau_meta: np.ndarray        # s, the time constant det_cal states (tau_eff): tau with its
    #                             measurement error, NaN where unmeasured
    dxi: np.ndarray             # rad, metadata xi minus true xi
    deta: np.ndarray            # rad, metadata eta minus true eta

    def subset(self, sel) -> "DetectorFlaws":
        return DetectorFlaws(**{f.name: getattr(self, f.name)[sel] for f in fields(self)})

    @property
    def ideal(self) -> bool:
        """Whether these detectors have no imperfection at all."""
        return bool(np.all(self.status == OK) and np.all(self.noise_factor == 1)
                    and not np.any(self.fknee) and not self.filters_sky
                    and not np.any(self.dxi) and not np.any(self.deta))

    @property
    def filters_sky(self) -> bool:
        """Whether the sky signal must be seen through calibration errors or time constants."""
        return bool(np.any(self.gain != 1) or np.any(self.tau > 0))


def _log_uniform(rng, low_high, size):
    low, high = low_high
    return np.exp(rng.uniform(np.log(low), np.log(high), size))


def _yield_status(cfg, n, rng):
    """Exactly round(fraction x n) dead and noisy detectors, chosen at random (disjoint)."""
    status = np.full(n, OK, dtype="U5")
    if cfg.dead_fraction == 0 and cfg.noisy_fraction == 0:
        return status
    order = rng.permutation(n)
    n_dead = int(round(cfg.dead_fraction * n))
    n_noisy = min(int(round(cfg.noisy_fraction * n)), n - n_dead)
    status[order[:n_dead]] = DEAD
    status[order[n_dead:n_dead + n_noisy]] = NOISY
    return status


def _gains(cfg, n, rng):
    if cfg.scatter == 0:
        return np.ones(n)
    draw = rng.standard_normal(n) * cfg.scatter
    return np.exp(draw) if cfg.distribution == "lognormal" else 1 + draw


def _group_flaws(config, band, n, rng_of) -> DetectorFlaws:
    """Flaws of the ``n`` detectors of one wafer-band; ``rng_of(component)`` gives its streams."""
    status = _yield_status(config.detector_yield, n, rng_of("yield"))
    lost = min(config.detector_yield.lost_detectors, n)
    if lost:
        status[rng_of("lost").choice(n, lost, replace=False)] = LOST
    factor = np.ones(n)
    if config.noise.white_scatter > 0:
        factor = np.exp(rng_of("white_scatter").standard_normal(n) * config.noise.white_scatter)
    factor[status == NOISY] *= config.detector_yield.noisy_factor
    fknee = (np.zeros(n) if config.noise.fknee is None
             else _log_uniform(rng_of("fknee"), config.noise.fknee, n))
    tau_range = config.time_constants.range_for(band)
    tau = np.zeros(n) if tau_range is None else 1e-3 * _log_uniform(rng_of("tau"), tau_range, n)
    tau_meta = tau.copy()
    cal = config.time_constants
    if cal.metadata_error > 0:
        tau_meta *= 1 + cal.metadata_error * rng_of("tau_error").standard_normal(n)
    if cal.metadata_nan > 0:
        tau_meta[rng_of("tau_nan").random(n) < cal.metadata_nan] = np.nan
    sigma = config.focal_plane_errors.sigma_arcsec * ARCSEC
    if sigma > 0:
        dxi, deta = rng_of("focal_plane").standard_normal((2, n)) * sigma
    else:
        dxi, deta = np.zeros(n), np.zeros(n)
    return DetectorFlaws(status, factor, fknee, _gains(config.calibration, n, rng_of("gain")),
                         tau, tau_meta, dxi, deta)


def draw_flaws(config, tube, dets, rng_for) -> DetectorFlaws:
    """Flaws of every detector of ``dets`` (one tube), drawn wafer-band by wafer-band;
    ``rng_for(*keys)`` gives the seeded generator of the flaws' stream ``keys``."""
    n = len(dets["readout_id"])
    out = DetectorFlaws(np.full(n, OK, dtype="U5"), *np.zeros((7, n)))
    for wafer, band in sorted(set(zip(dets["wafer_slot"], dets["bandpass"]))):
        sel = np.flatnonzero((dets["wafer_slot"] == wafer) & (dets["bandpass"] == band))
        group = _group_flaws(config, band, len(sel),
                             lambda component: rng_for(component, tube, wafer, band))
        for f in fields(out):
            getattr(out, f.name)[sel] = getattr(group, f.name)
    return out


def metadata_positions(dets, flaws: DetectorFlaws) -> dict:
    """``dets`` with xi, eta as the metadata state them (true plus the focal-plane errors)."""
    return dict(dets, xi=dets["xi"] + flaws.dxi, eta=dets["eta"] + flaws.deta)


def flaws_table(dets, flaws: DetectorFlaws) -> Table:
    """Truth table of the detectors' imperfections, with units."""
    table = Table({"readout_id": dets["readout_id"], "det_id": dets["det_id"],
                   "tube_slot": dets["tube_slot"], "wafer_slot": dets["wafer_slot"],
                   "bandpass": dets["bandpass"], "status": flaws.status,
                   "noise_factor": flaws.noise_factor, "fknee": flaws.fknee * u.Hz,
                   "gain": flaws.gain, "tau": flaws.tau * u.s, "tau_eff": flaws.tau_meta * u.s,
                   "xi_true": dets["xi"] * u.rad, "eta_true": dets["eta"] * u.rad,
                   "dxi": flaws.dxi / ARCSEC * u.arcsec, "deta": flaws.deta / ARCSEC * u.arcsec})
    table.meta["comments"] = [
        "status: ok, dead, noisy or lost (NaN throughout); noise_factor: white and 1/f noise "
        "over the band's level",
        "gain: true sky response over the metadata's; tau: one-pole detector time constant; "
        "tau_eff: the one det_cal states",
        "dxi, deta: metadata focal-plane position minus the true one (xi_true, eta_true)"]
    return table


def low_pass(row, tau, dt):
    """``row`` seen through the one-pole filter 1/(1 + 2 pi i f tau) (float64 result).

    The straight line through the first and last samples is taken out first and its exact
    response (the line delayed by tau) put back, so the periodic FFT sees no step at the ends;
    the padding holds the filter's decay (20 tau) so nothing wraps around.
    """
    n = len(row)
    t = np.arange(n) * dt
    slope = (float(row[-1]) - float(row[0])) / (t[-1] if n > 1 else 1.0)
    line = float(row[0]) + slope * t
    nfft = fft.next_fast_len(n + int(np.ceil(20 * tau / dt)) + 1, real=True)
    freq = fft.rfftfreq(nfft, dt)
    filtered = fft.irfft(fft.rfft(row - line, nfft) / (1 + 2j * np.pi * freq * tau), nfft)[:n]
    return filtered + line - slope * tau


def respond_to_sky(sky, flaws: DetectorFlaws, dt):
    """Turn the sky signal ``sky`` (rows of ``flaws``' detectors) into what the detectors record:
    times the true calibration, through the time constant. In place."""
    for i in range(len(sky)):
        if flaws.gain[i] != 1:
            sky[i] *= np.float32(flaws.gain[i])
        if flaws.tau[i] > 0:
            sky[i] = low_pass(sky[i], flaws.tau[i], dt)


def one_over_f(rng, n, dt, fknee, alpha):
    """Gaussian noise of unit white level whose power spectrum is (fknee / f)^alpha (no mean)."""
    spectrum = fft.rfft(rng.standard_normal(n))
    freq = fft.rfftfreq(n, dt)
    spectrum[0] = 0
    spectrum[1:] *= (fknee / freq[1:]) ** (alpha / 2)
    return fft.irfft(spectrum, n)


def silence_dead(tod, flaws: DetectorFlaws, cfg, readout_noise=None):
    """Overwrite the rows of dead detectors with what they record (``cfg``: detector_yield),
    plus ``readout_noise(row)`` (an array of the row's length) where given, and the rows of
    lost channels with NaN. The readout's jumps and the cosmic rays are added after this."""
    value = {"zeros": 0.0, "nan": np.nan, "constant": cfg.dead_value}[cfg.dead_mode]
    for row in np.flatnonzero(flaws.status == DEAD):
        tod[row] = value
        if readout_noise is not None and cfg.dead_mode != "nan":
            tod[row] += readout_noise(row).astype(tod.dtype)
    tod[flaws.status == LOST] = np.nan
