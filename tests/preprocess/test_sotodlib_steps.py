"""The chunked standard steps against sotodlib's own, through sotodlib's Pipeline on a real
wafer (every imperfection at once, studies/configs/real_wafer.yaml, two seeds): the same
filtered signal, glitch flags and significances, to float32 rounding (FFTW may round a row
differently in batches of another size or with other threads; here they are bit-identical)."""
import numpy as np
import pytest
import yaml
from sotodlib import core
from sotodlib.preprocess import Pipeline

from so_transients.campaign.real_wafer import simulate_seed
from so_transients.common.step_config import ConfigError
from so_transients.site.pipeline import PRODUCTION

PIPE = yaml.safe_load(PRODUCTION.read_text())["process_pipe"]
NAMES = [step["name"] for step in PIPE]
#: the production config's time-constant deconvolution, glitch flags and low-pass copy
TIMECONST = NAMES.index("transient_fourier_filter")
GLITCHES = NAMES.index("transient_glitches")
LOW_PASS = len(NAMES) - 1 - NAMES[::-1].index("transient_fourier_filter")


def as_sotodlibs(step):
    """The same config block for sotodlib's step."""
    return dict(step, name=step["name"].replace("transient_", ""))


@pytest.fixture(scope="module", params=[3, 9])
def wafer(request, module_tmp):
    """Five minutes of a real wafer after the production config's steps before the
    time-constant deconvolution (NaN detectors and samples still in)."""
    sim = simulate_seed(module_tmp("steps"), seed=request.param, duration=300.0,
                        flares=[])
    aman = core.Context(str(sim.context)).get_obs(sim.obs_ids[0])
    Pipeline(PIPE[:TIMECONST]).run(aman)
    return aman


def same_to_float32(ours, theirs):
    """Equal NaN, and equal values to float32 rounding of each detector's scale."""
    ours, theirs = np.asarray(ours), np.asarray(theirs)
    assert np.array_equal(np.isnan(ours), np.isnan(theirs))
    scale = np.nanmax(np.abs(theirs), axis=1, keepdims=True)
    assert np.nanmax(np.abs(ours - theirs) / np.where(scale > 0, scale, 1.0)) < 1e-6


def twice(aman, step):
    """``step`` run by sotodlib's version and ours on copies of ``aman``: both AxisManagers
    and their archive entries."""
    out = []
    for block in (as_sotodlibs(step), step):
        copy = aman.copy()
        for name in ("signal", "lpf_signal"):
            if name in aman._fields:
                copy.move(name, None)
                copy.wrap(name, np.array(aman[name]), [(0, "dets"), (1, "samps")])
        proc = Pipeline([block]).run(copy)[0]
        out.append((copy, proc))
    return out


@pytest.mark.slow
def test_the_time_constant_deconvolution_is_sotodlibs(wafer):
    (theirs, _), (ours, _) = twice(wafer, PIPE[TIMECONST])
    assert np.isnan(theirs.signal).any()          # the lost detector and the NaN stretch
    same_to_float32(ours.signal, theirs.signal)


@pytest.mark.slow
def test_the_low_passed_copy_is_sotodlibs(wafer):
    step = PIPE[LOW_PASS]
    assert step["wrap_name"] == "lpf_signal"
    (theirs, _), (ours, _) = twice(wafer, step)
    same_to_float32(ours.lpf_signal, theirs.lpf_signal)
    assert np.array_equal(np.asarray(ours.signal), np.asarray(wafer.signal), equal_nan=True)


@pytest.mark.slow
def test_the_glitch_flags_and_significances_are_sotodlibs(wafer):
    (theirs, proc_theirs), (ours, proc_ours) = twice(wafer, PIPE[GLITCHES])
    a, b = proc_theirs.glitches, proc_ours.glitches
    assert a.glitch_detection.nnz > 100                 # cosmic rays on a real wafer
    assert a.glitch_detection.shape == b.glitch_detection.shape
    assert len(a.glitch_flags) == len(b.glitch_flags) == wafer.dets.count
    # a sample at the threshold may flip with float32 rounding: at most 1 in 1000 of them
    flagged = [x.mask() != y.mask() for x, y in zip(a.glitch_flags, b.glitch_flags)]
    assert np.sum(flagged) <= 1e-3 * sum(x.mask().sum() for x in a.glitch_flags)
    both = (a.glitch_detection != 0).multiply(b.glitch_detection != 0)
    assert both.nnz >= 0.999 * a.glitch_detection.nnz
    diff = abs(a.glitch_detection - b.glitch_detection).multiply(both)
    assert diff.max() <= 1e-5 * abs(a.glitch_detection).max()
    # sotodlib's select on them: the same detectors kept
    select = {"max_n_glitch": 2, "sig_glitch": 10, "max_t_frac": 0.01}
    keep = [Pipeline.PIPELINE[name]({"name": name, "calc": {}, "select": select})
            .select(theirs, proc, in_place=False)
            for name, proc in (("glitches", proc_theirs), ("transient_glitches", proc_ours))]
    assert 0 < keep[0].sum() < len(keep[0]) and np.array_equal(*keep)


def test_chunks_must_be_a_positive_number_of_detectors():
    for name, block in (("transient_fourier_filter", "process"),
                        ("transient_glitches", "calc")):
        with pytest.raises(ConfigError, match=f"{name}: chunk_dets"):
            Pipeline([{"name": name, block: {"chunk_dets": 0}}])


def test_an_unknown_filter_is_refused_when_the_pipeline_is_built():
    with pytest.raises(ConfigError, match="no filter 'low_pass_butter5'"):
        Pipeline([{"name": "transient_fourier_filter",
                   "process": {"filt_function": "low_pass_butter5"}}])


#: timeconst_filter without ``timeconst`` reads the field ``timeconst``; two filters naming one
#: field read it once
FILTER_CHAINS = [
    [{"name": "timeconst_filter", "filter_params": {"invert": True}}],
    [{"name": "timeconst_filter", "filter_params": {"timeconst": "timeconst", "invert": True}},
     {"name": "timeconst_filter", "filter_params": {"timeconst": "timeconst", "invert": True}}],
]


@pytest.mark.parametrize("filters", FILTER_CHAINS)
def test_a_filter_reads_the_fields_its_arguments_name_or_default_to(filters):
    """As sotodlib's step, with a chunk size that does not divide the detectors."""
    rng = np.random.default_rng(5)
    ndet, nsamp = 11, 4000
    aman = core.AxisManager(core.LabelAxis("dets", [f"d{i}" for i in range(ndet)]),
                            core.OffsetAxis("samps", nsamp))
    aman.wrap("timestamps", np.arange(nsamp) / 200.0, [(0, "samps")])
    aman.wrap("signal", rng.standard_normal((ndet, nsamp)).astype(np.float32),
              [(0, "dets"), (1, "samps")])
    aman.wrap("timeconst", rng.uniform(0.001, 0.005, ndet), [(0, "dets")])
    aman.wrap("iir_params", core.AxisManager())           # Pipeline.run reads it
    out = []
    for name, extra in (("fourier_filter", {}), ("transient_fourier_filter", {"chunk_dets": 4})):
        copy = aman.copy()
        copy.move("signal", None)
        copy.wrap("signal", np.array(aman.signal), [(0, "dets"), (1, "samps")])
        Pipeline([{"name": name, "process": {"filters": filters, **extra}}]).run(copy)
        out.append(np.asarray(copy.signal))
    assert not np.allclose(out[0], aman.signal, atol=1e-3)   # it filtered
    same_to_float32(out[1], out[0])


@pytest.mark.slow
def test_on_a_real_wafer_the_production_pca_cleans_as_sotodlibs(wafer):
    """The production config's steps up to the PCA, then its 10 modes by either step (ours
    in blocks, sotodlib's ``pca_filter``): the same cleaned detectors."""
    k = NAMES.index("transient_pca_filter")
    aman = wafer.copy()                    # deep: the other tests keep the module's wafer
    Pipeline(PIPE[TIMECONST:k]).run(aman)
    signal, model = np.array(aman.signal), np.array(aman.lpf_signal)
    Pipeline([dict(PIPE[k], name="pca_filter")]).run(aman)
    theirs = np.array(aman.signal)
    aman.signal[...], aman.lpf_signal[...] = signal, model
    Pipeline([PIPE[k]]).run(aman)
    residual = np.std(theirs, axis=1)
    live = residual > 0
    assert live.sum() > 500
    # measured: 1e-4 of each detector's cleaned noise at most (float32 rounding)
    change = np.std(np.asarray(aman.signal) - theirs, axis=1)[live] / residual[live]
    assert change.max() < 1e-3
