"""transient_pca_filter against sotodlib's pca_filter: the same cleaned signal, block by
block, through sotodlib's Pipeline; a NaN detector left out instead of spread to all."""
import numpy as np
import pytest
from sotodlib import core
from sotodlib.preprocess import Pipeline

import so_transients  # noqa: F401  registers the steps
from so_transients.detect.pca import covariance, pca_filter

NDET, NSAMP, NMODES = 120, 30_000, 3
#: the common modes are random walks ~ sqrt(NSAMP) = 170 times the white noise: float32
#: keeps them to 6e-8, so two correct subtractions agree to a few 1e-5 of the noise
TOLERANCE = 2e-4


def wafer(seed=0):
    """Detectors seeing NMODES common modes (well separated from the unit white noise) with
    gains near 1, and a low-passed copy of the signal as the model."""
    rng = np.random.default_rng(seed)
    common = np.cumsum(rng.standard_normal((NMODES, NSAMP)), axis=1)
    gains = rng.normal(1.0, 0.1, (NDET, NMODES))
    signal = (gains @ common + rng.standard_normal((NDET, NSAMP))).astype(np.float32)
    kernel = np.ones(21) / 21
    model = np.array([np.convolve(row, kernel, mode="same") for row in signal], np.float32)
    aman = core.AxisManager(core.LabelAxis("dets", [f"d{i}" for i in range(NDET)]),
                            core.OffsetAxis("samps", NSAMP))
    aman.wrap("signal", signal, [(0, "dets"), (1, "samps")])
    aman.wrap("lpf_signal", model, [(0, "dets"), (1, "samps")])
    aman.wrap("iir_params", core.AxisManager())
    return aman


def run(aman, step):
    Pipeline([{"name": step, "model_signal": "lpf_signal", "signal": "signal",
               "process": {"n_modes": NMODES}}]).run(aman)
    return np.asarray(aman.signal)


def test_the_covariance_in_blocks_is_numpys():
    model = np.asarray(wafer().lpf_signal)
    rows = np.arange(NDET)
    ours, numpys = covariance(model, rows, 4096), np.cov(model)
    assert np.abs(ours - numpys).max() < 1e-6 * np.abs(numpys).max()


@pytest.mark.parametrize("seed", [0, 1])
def test_the_step_cleans_as_sotodlibs_pca_filter(seed):
    raw = np.std(wafer(seed).signal)
    theirs, ours = run(wafer(seed), "pca_filter"), run(wafer(seed), "transient_pca_filter")
    assert np.std(theirs) < 0.05 * raw              # the common modes are (mostly) gone
    assert np.abs(ours - theirs).max() < TOLERANCE * np.std(theirs)


def test_the_model_signal_defaults_to_the_signal_itself():
    a, b = wafer(), wafer()
    Pipeline([{"name": "pca_filter", "process": {"n_modes": NMODES}}]).run(a)
    Pipeline([{"name": "transient_pca_filter", "process": {"n_modes": NMODES}}]).run(b)
    assert np.abs(np.asarray(a.signal) - np.asarray(b.signal)).max() < TOLERANCE


def test_a_nan_detector_is_left_out_not_spread(caplog):
    aman, clean = wafer(), wafer()
    aman.lpf_signal[7, 100:200] = np.nan
    before = np.array(aman.signal[7])
    with caplog.at_level("WARNING"):
        ours = run(aman, "transient_pca_filter")
    assert "1 of 120 detectors" in caplog.text and "lpf_signal" in caplog.text
    assert np.array_equal(ours[7], before) and np.isfinite(ours).all()
    # the others: as sotodlib cleans them without that detector
    keep = np.arange(NDET) != 7
    theirs = run(clean.restrict("dets", clean.dets.vals[keep], in_place=False),
                 "pca_filter")
    assert np.abs(ours[keep] - theirs).max() < TOLERANCE * np.std(theirs)


def test_too_few_finite_detectors_is_an_error_naming_the_step_and_group():
    signal = np.zeros((2, 100), np.float32)
    with pytest.raises(ValueError, match="2 detectors .* fewer than the 3 PCA modes"):
        pca_filter(signal, signal, 3)
    aman = wafer()
    aman.lpf_signal[3:] = np.nan                    # 3 finite detectors, 3 modes: still runs
    run(aman, "transient_pca_filter")
    aman.lpf_signal[2] = np.nan
    with pytest.raises(ValueError, match=r"transient_pca_filter: unknown observation "
                                         r"\(all detectors\): 2 detectors"):
        run(aman, "transient_pca_filter")
