"""The beam fit's measured error scale, in each scan direction.

The fit's covariance treats detectors as independent; they share residual atmosphere, so
its errors are too small by a factor measured on the data: the spread of ``A / sigma_A`` of
amplitude fits at random (null) positions (:func:`null_scatter`). Paper mode keeps fits at
``A / sigma_A`` of 5 such scales, where a scale off by e changes the rate of noise passing
by about exp(25 e).

**Per scan direction.** Wind carries the atmosphere across the array at a different speed
relative to the detectors when the telescope scans with it than against it, so the
atmosphere left above the matched filter's high-pass, and with it the scale, differs
between sweeps of increasing azimuth (sotodlib's ``flags.right_scan``, direction +1) and of
decreasing azimuth (``left_scan``, -1). On 30 minutes of noise on the project's
simulated wafer the right-going sweeps' scale was 1.17 times the left-going ones' with ideal
detectors and 1.25 times on a drawn real wafer, every right-going sweep's above every
left-going one's (docs/results/drawn_wafers.md): one scale for both lets the noisier
direction's fluctuations through at several times the rate of the other. :class:`ErrorScale` holds one
scale per direction, :func:`measure_error_scales` measures both, each on null positions of
its own direction only.

**Away from sources, not away from their times.** A null fit must not sit on a source,
whose flux would widen the spread; it need not avoid the rest of the data at the source's
time. :class:`Sources` are what the null positions keep clear of: within ``margin`` s of a
source's time span *and* within ``radius`` of its position. (Excluding whole seconds around
every candidate that passed the cuts, as before, left out much of a drawn wafer's data,
and mostly its noisier stretches, where noise candidates are found: the scale came out
low.)
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from so_transients.common import pointing
from so_transients.common.angles import sky_separation
from so_transients.common.robust import clipped_std
from so_transients.common.scan_geometry import samples_in
from so_transients.detect.fit import FitConfig, FitInputs, fit_window, null_ratio, window_arrays

#: The two scan directions: +1 where the azimuth increases (sotodlib's ``flags.right_scan``),
#: -1 where it decreases (``flags.left_scan``)
DIRECTIONS = (1, -1)


@dataclass(frozen=True)
class ErrorScale:
    """The fit's error scale in sweeps of increasing azimuth (``right``) and of decreasing
    azimuth (``left``)."""

    right: float
    left: float

    @classmethod
    def of(cls, value) -> "ErrorScale | None":
        """``value`` as an :class:`ErrorScale`: one number (or a list of one) for both
        directions, a pair ``[right, left]``, an ErrorScale, or None (None)."""
        if value is None or isinstance(value, ErrorScale):
            return value
        values = np.atleast_1d(np.asarray(value, float))
        right, left = (values[0], values[0]) if values.size == 1 else values
        return cls(float(right), float(left))

    def at(self, direction) -> float:
        """The scale of scan ``direction`` (+1 or -1)."""
        return self.right if direction > 0 else self.left

    def with_value(self, direction, value) -> "ErrorScale":
        """This scale with scan ``direction``'s replaced by ``value``."""
        return replace(self, **{"right" if direction > 0 else "left": float(value)})

    @property
    def largest(self) -> float:
        return max(self.right, self.left)

    def as_list(self) -> list:
        """``[right, left]``, as a config's ``error_scale`` takes it."""
        return [self.right, self.left]


@dataclass(frozen=True)
class Sources:
    """What null fits keep clear of: sources seen from ``t_lo`` to ``t_hi`` (ctime) at
    (``ra``, ``dec``) (radians), one entry each."""

    t_lo: np.ndarray
    t_hi: np.ndarray
    ra: np.ndarray
    dec: np.ndarray

    @classmethod
    def none(cls) -> "Sources":
        empty = np.zeros(0)
        return cls(empty, empty, empty, empty)

    @classmethod
    def of_candidates(cls, cands, rows) -> "Sources":
        """The candidates ``rows`` (indices or a mask) of a group's candidate columns: each
        cluster's time span and mean position."""
        pick = lambda name: np.asarray(cands[name], float)[rows]
        return cls(pick("t_start"), pick("t_stop"), pick("cluster_ra"), pick("cluster_dec"))

    @classmethod
    def at(cls, times, ra, dec) -> "Sources":
        """Sources seen at ``times`` at (``ra``, ``dec``) (one position, or one per time)."""
        times = np.asarray(times, float)
        return cls(times, times, np.broadcast_to(ra, times.shape).astype(float),
                   np.broadcast_to(dec, times.shape).astype(float))

    @classmethod
    def join(cls, parts) -> "Sources":
        """One :class:`Sources` of all of ``parts``."""
        parts = list(parts) + [cls.none()]
        return cls(*(np.concatenate([getattr(p, k) for p in parts])
                     for k in ("t_lo", "t_hi", "ra", "dec")))

    def near(self, t, ra, dec, margin, radius) -> np.ndarray:
        """Whether each of the positions (``ra``, ``dec``) at times ``t`` lies within
        ``margin`` s of a source's time span and within ``radius`` (rad) of its position."""
        t, ra, dec = (np.asarray(v, float) for v in (t, ra, dec))
        out = np.zeros(len(t), bool)
        for k in range(len(self.t_lo)):
            when = (t >= self.t_lo[k] - margin) & (t <= self.t_hi[k] + margin)
            if when.any():
                where = np.flatnonzero(when)
                out[where] |= sky_separation(ra[where], dec[where], self.ra[k],
                                             self.dec[k]) <= radius
        return out


#: Null positions keep this far (s) from a source's time span ...
AVOID_MARGIN = 2.0
#: ... when also within this many beam FWHM of its position (the beam model at 3 FWHM is
#: exp(-4 ln2 x 9) = 1e-11 of its peak)
AVOID_FWHM = 3.0


def null_scatter(windows, inflation=1.0):
    """Robust spread of ``A / sigma_A`` for amplitude fits at fixed (null) positions.

    ``windows``: ``(track, det_xi, det_eta, amp, sigma_amp)`` per random position away from
    any source, as :func:`so_transients.detect.fit.fit_candidate` takes them; the result is
    the factor by which the naive, inflated errors must grow to describe the actual noise
    (1 for independent detectors).

    The spread is the standard deviation within 5 MADs (:func:`clipped_std`), not the MAD
    itself: every fitted S/N is divided by it, and at a cut of 5 an error of e in the scale
    changes the rate of noise passing it by about exp(25 e). The MAD of 200 null fits is
    known to 8 % (37 % efficiency), which let noise-only drawn wafers make anywhere from
    2 to 10 detections in the same 30 minutes depending on the null positions drawn
    (docs/results/drawn_wafers.md); the clipped standard deviation is known to 5 % from 200,
    1.6 % from 2000 (``n_null``).
    """
    ratios = [r for r in (null_ratio(w, inflation) for w in windows) if np.isfinite(r)]
    if len(ratios) < 10:
        return 1.0
    return clipped_std(ratios)


def measure_error_scale(data: FitInputs, band_dets, sources: Sources, cfg: FitConfig,
                        direction, around=None):
    """Measured spread of the fitted amplitude (:func:`null_scatter`) at ``cfg.n_null``
    random positions of the live detectors of ``band_dets`` in sweeps of scan ``direction``
    (+1, -1), clear of ``sources`` (:class:`Sources`; within :data:`AVOID_MARGIN` s of one's
    time and :data:`AVOID_FWHM` beam FWHM of its position). With ``around`` (a time): at
    ``cfg.n_null_local`` positions within ``cfg.local_window`` seconds of it instead (1.0
    when fewer than 100 can be fitted there)."""
    dets = band_dets[~data.dead[band_dets]]
    t = data.timestamps
    rng = np.random.default_rng(cfg.seed)
    n_win = samples_in(t, cfg.window)
    lo_ok, hi_ok = n_win + 1, len(t) - n_win - 1
    n_null = cfg.n_null
    if around is not None:
        lo_ok = max(lo_ok, int(np.searchsorted(t, around - cfg.local_window)))
        hi_ok = min(hi_ok, int(np.searchsorted(t, around + cfg.local_window)))
        n_null = cfg.n_null_local
    pool = np.arange(lo_ok, hi_ok)
    pool = pool[data.direction[pool] == np.sign(direction)] if len(pool) else pool
    if not len(dets) or not len(pool):
        return 1.0
    centers = rng.choice(pool, size=4 * n_null)
    picks = rng.choice(dets, size=len(centers))
    ra, dec = pointing.radec_of_samples(data.bore_q, data.xi, data.eta, picks, centers)
    fwhm = float(np.median(data.beam_sigma[dets])) * np.sqrt(8 * np.log(2))
    clear = ~sources.near(t[centers], ra, dec, AVOID_MARGIN, AVOID_FWHM * fwhm)
    keep = np.flatnonzero(clear)[:n_null]
    if around is not None and len(keep) < 100:
        return 1.0
    windows = []
    for k in keep:
        lo, hi = centers[k] - n_win, centers[k] + n_win + 1
        _, track, near = fit_window(data, ra[k], dec[k], lo, hi, dets, cfg)
        windows.append(window_arrays(data, track, near, lo, hi))
    return null_scatter(windows, data.kernel(dets)[1])


def measure_error_scales(data: FitInputs, band_dets, sources: Sources,
                         cfg: FitConfig) -> ErrorScale:
    """:func:`measure_error_scale` in each scan direction (``cfg.n_null`` positions each)."""
    right, left = (measure_error_scale(data, band_dets, sources, cfg, d) for d in DIRECTIONS)
    return ErrorScale(right, left)


def median_scales(scales, directions) -> ErrorScale | None:
    """The median of fitted candidates' ``error_scale`` in each scan direction (their
    ``direction`` column), as the group's :class:`ErrorScale`; None when a direction has
    none."""
    scales, directions = np.asarray(scales, float), np.asarray(directions)
    ok = np.isfinite(scales)
    medians = [float(np.median(scales[ok & (directions == d)]))
               if np.any(ok & (directions == d)) else None for d in DIRECTIONS]
    return None if None in medians else ErrorScale(*medians)
