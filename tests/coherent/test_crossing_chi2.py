"""The chi-squared test of a coherent maximum: noise and sources pass, a few detectors'
spikes fail, and the background ranks a candidate among maxima that were tested alike."""
import numpy as np
import pytest
from scipy.stats import chi2 as chi2_law

from so_transients.coherent.config import CoherentConfig
from so_transients.coherent.statistic import coherent_map, row_offsets, row_weights
from so_transients.coherent.crossing_chi2 import chi2_limit, crossing_chi2, detector_groups
from so_transients.significance.far import Background

from tests.coherent.test_coherent import FS, SIGMA_BEAM, SPEED, inject, matched_pulse, wafer
from tests.coherent.test_coherent_find import NSAMP, found

BINS = CoherentConfig().chi2_bins


def test_noise_follows_the_chi2_law_of_bins_minus_one_degrees_of_freedom():
    rng = np.random.default_rng(11)
    geometry, sigma = wafer(rng=rng)
    snr = rng.normal(size=(len(sigma), NSAMP))
    rows = row_offsets(geometry, SIGMA_BEAM, CoherentConfig().row_step)
    weights, _ = row_weights(geometry, rows, SIGMA_BEAM, sigma, np.ones(len(sigma), bool))
    lags = geometry.lag_samples
    n = 3000
    r, t = rng.integers(len(rows), size=n), rng.integers(200, NSAMP - 200, size=n)
    c = crossing_chi2(snr, weights, detector_groups(weights, geometry, BINS), BINS, lags, r, t)
    # independent groups of independent unit-variance S/N: mean bins - 1, variance
    # 2 (bins - 1); positions overlap, so allow 5 standard errors of n values
    assert abs(c.mean() - (BINS - 1)) < 5 * np.sqrt(2 * (BINS - 1) / n)
    # the tail the test cuts: its share of noise positions, within Poisson errors
    limit = chi2_law.isf(1e-2, BINS - 1)
    assert abs(np.mean(c > limit) - 1e-2) < 5 * np.sqrt(1e-2 / n)


@pytest.mark.parametrize("flux, ramp", [(150.0, 1.0), (600.0, 1.0), (600.0, 3.0)])
def test_a_source_crossing_passes_even_when_its_flux_changes_within_the_crossing(flux, ramp):
    """A steady source, a bright one, and one whose flux triples while it crosses (a 0.5 s
    flare): the groups take detectors from the whole crossing, so each keeps its share."""
    rng = np.random.default_rng(12)
    geometry, sigma = wafer(rng=rng)
    rows = row_offsets(geometry, SIGMA_BEAM, CoherentConfig().row_step)
    c = rows[len(rows) // 2] + 0.3 * SIGMA_BEAM          # between rows
    snr = rng.normal(size=(len(sigma), NSAMP))
    lags = geometry.lag_samples
    span = np.ptp(lags)
    profile = ramp ** ((lags - lags.min()) / span)         # 1 to ramp across the crossing
    inject(snr, geometry, sigma * np.mean(profile) / profile, flux, 2000, c)
    z, _ = coherent_map(snr, geometry, rows, SIGMA_BEAM, sigma, np.ones(len(sigma), bool))
    r, t = np.unravel_index(np.nanargmax(z), z.shape)
    weights, _ = row_weights(geometry, rows, SIGMA_BEAM, sigma, np.ones(len(sigma), bool))
    value = crossing_chi2(snr, weights, detector_groups(weights, geometry, BINS), BINS, lags,
                          [r], [t])[0]
    cfg = CoherentConfig()
    assert z[r, t] > 10
    assert value <= chi2_limit(z[r, t], BINS, cfg.chi2_tail, cfg.chi2_mismatch)


def test_a_few_detectors_spikes_fail_the_test_where_the_other_vetoes_pass_them():
    """Three detectors crossed far apart in time, each a third of the sum: no single one
    makes half of it and they are not at one instant, so only the chi-squared test removes
    the maximum they make."""
    rng = np.random.default_rng(13)
    geometry, sigma = wafer(rng=rng)
    snr = rng.normal(size=(len(sigma), NSAMP))
    rows = row_offsets(geometry, SIGMA_BEAM, CoherentConfig().row_step)
    c = rows[len(rows) // 2]
    lags = geometry.lag_samples
    offset = np.abs(geometry.across - c)
    near = np.flatnonzero(offset <= offset.min() + 0.01 * SIGMA_BEAM)   # a line of the grid
    spiked = near[np.argsort(lags[near])][[0, len(near) // 2, -1]]
    width = SIGMA_BEAM / SPEED * FS
    for d in spiked:
        snr[d] += 9.0 * matched_pulse(NSAMP, 2000 + lags[d], width)
    at = lambda peaks: [p for p in peaks if abs(p["sample"] - 2000) <= 3]
    assert at(found(snr, geometry, sigma, chi2_bins=0))        # the other vetoes keep it
    assert not at(found(snr, geometry, sigma))


def test_a_candidate_is_ranked_among_the_maxima_tested_alike():
    rng = np.random.default_rng(14)
    slides = 4.5 + rng.exponential(0.4, 2000)
    ok = slides < 6.0                              # the highest fail the test
    b = Background(slides, 20.0, np.zeros(0), 1.0, ok, np.zeros(0, bool), slide_floor=4.5)
    z = np.array([5.0, 6.5, 6.5])
    far = b.far(z, [True, True, False])["far_slides"]
    assert far[0] == pytest.approx(np.sum(slides[ok] >= 5.0) / 20.0)
    assert far[1] == pytest.approx(0.5 / 20.0)    # none tested alike is as high: half a count
    assert far[2] == pytest.approx(np.sum(slides >= 6.5) / 20.0) and far[2] > far[1]
