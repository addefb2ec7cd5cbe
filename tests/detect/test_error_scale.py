"""The fit's error scale in each scan direction, measured clear of sources
(:mod:`so_transients.detect.error_scale`)."""
import numpy as np
import pytest

from so_transients.common import pointing
from so_transients.common.angles import ARCMIN
from so_transients.common.bands import get_band
from so_transients.common.scan_geometry import constant_velocity, scan_direction
from so_transients.detect.error_scale import (
    ErrorScale, Sources, measure_error_scales, median_scales
)
from so_transients.detect.fit import FitConfig, FitInputs
from so_transients.sim.scan import ScanPattern, boresight

T0 = 1_700_000_000.0


def noise_group(right_factor, duration=240.0, fs=50.0, seed=1):
    """A 12 x 12 grid of f090 detectors 1' apart scanning 12 s sweeps, white S/N noise whose
    spread is ``right_factor`` times larger in sweeps of increasing azimuth than in the
    others (the filter's own normalization is one number per detector)."""
    t_rel = np.arange(0, duration, 1 / fs)
    t = T0 + t_rel
    az, el, _ = boresight(t_rel, ScanPattern(sweep_time=12.0))
    grid = (np.arange(12) - 5.5) * ARCMIN
    xi, eta = (v.ravel() for v in np.meshgrid(grid, grid))
    ndet, sigma = len(xi), get_band("f090").sigma
    direction = scan_direction(az)
    snr = np.random.default_rng(seed).normal(0, 1, (ndet, len(t)))
    snr[:, direction > 0] *= right_factor
    sigma_t = sigma / np.radians(ScanPattern().sky_speed)
    lags = np.arange(-30, 31) / fs
    response = np.tile(np.exp(-0.5 * (lags / sigma_t) ** 2), (ndet, 1))
    return FitInputs(t, pointing.boresight_quats(t, az, el), xi, eta, snr.astype(np.float32),
                     np.full(ndet, 50.0), np.zeros(ndet, bool), np.full(ndet, sigma),
                     np.ones(ndet), lags, response, constant_velocity(t, az, el, 0.1),
                     direction=direction)


def test_each_scan_direction_gets_the_scale_of_its_own_noise():
    """Noise 1.3 times larger in right-going sweeps: one scale for both would put the two
    directions' S/N 14 % off in opposite ways; each direction's measured alone, their ratio
    is 1.3 within the 2 x 2.2 % that 1000 null fits each allow (3 sigma)."""
    data = noise_group(1.3)
    scale = measure_error_scales(data, np.arange(len(data.xi)), Sources.none(),
                                 FitConfig(n_null=1000))
    assert scale.right / scale.left == pytest.approx(1.3, rel=3 * np.sqrt(2) * 0.022)
    same = measure_error_scales(noise_group(1.0), np.arange(len(data.xi)), Sources.none(),
                                FitConfig(n_null=1000))
    assert same.right / same.left == pytest.approx(1.0, abs=3 * np.sqrt(2) * 0.022)


def test_null_positions_keep_clear_of_a_source_in_time_and_on_the_sky_only():
    sources = Sources.at([100.0], 1.0, 0.5)
    t = np.array([100.0, 100.0, 103.0, 101.5])
    ra = np.array([1.0, 1.0 + 10 * ARCMIN, 1.0, 1.0 + 2 * ARCMIN])
    dec = np.full(4, 0.5)
    near = sources.near(t, ra, dec, margin=2.0, radius=6 * ARCMIN)
    # at it; at its time but 10' (6.4' on the sky) away; at its place 3 s later; 1.3' away
    assert near.tolist() == [True, False, False, True]
    assert not Sources.none().near(t, ra, dec, 2.0, 6 * ARCMIN).any()
    joined = Sources.join([sources, Sources.at([5.0, 6.0], [0.1, 0.2], 0.3)])
    assert joined.t_lo.tolist() == [100.0, 5.0, 6.0] and joined.dec.tolist() == [0.5, 0.3, 0.3]


def test_an_error_scale_is_one_number_or_one_per_direction():
    assert ErrorScale.of(1.5) == ErrorScale(1.5, 1.5) == ErrorScale.of([1.5])
    scale = ErrorScale.of([1.8, 1.4])
    assert (scale.at(1), scale.at(-1), scale.largest) == (1.8, 1.4, 1.8)
    assert scale.with_value(-1, 1.6) == ErrorScale(1.8, 1.6)
    assert ErrorScale.of(scale.as_list()) == scale and ErrorScale.of(None) is None
    assert median_scales([1.5, 2.5, 1.3, np.nan], [1, 1, -1, -1]) == ErrorScale(2.0, 1.3)
    assert median_scales([1.7, 1.9], [1, 1]) is None        # nothing fitted going left
