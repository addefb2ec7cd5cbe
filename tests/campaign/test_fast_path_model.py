"""The fast injection path's signal model against the full preprocessing, detector by detector.

A flare simulated into the TOD and run through the paper config's standard steps (the time
constants, the low-pass, the PCA's mask and the PCA, the matched filter) adds to each
detector's S/N what the fast path computes for it from the noise-only group: the same flares
in the same noise, so the difference of the two S/N timestreams is the flare's alone. Before
the fast path modelled the PCA it gave 2-10 % more S/N than the pipeline, and found flares
near the threshold that the pipeline did not (McNemar p = 0.012 at f090, issue 48).
"""
import numpy as np
import pytest
import yaml
from astropy.table import Table
from sotodlib import core
from sotodlib.preprocess import Pipeline

from so_transients.campaign.config import Injection
from so_transients.campaign.flare_injection import injected_windows
from so_transients.campaign.noise import Group, GroupState, prepare_group
from so_transients.campaign.noise_model import filtered_snr
from so_transients.campaign.search_steps import split_pipe
from so_transients.common.bands import fwhm_to_sigma, get_band
from so_transients.sim.sources import source_crossings
from so_transients.site.pipeline import CONFIGS
from tests.conftest import run_sim

pytestmark = pytest.mark.slow   # simulates and preprocesses twice

DURATION = 240.0
#: flares at a detector each (s after the start, mJy): near the f090 threshold at t_r = 0.5 s
#: (a few per detector), and bright ones the PCA's mask hides in part
FLARES = [(40.0, 400.0, "w16_f090_p010A"), (80.0, 1500.0, "w16_f090_p200B"),
          (120.0, 5000.0, "w16_f090_p350A"), (160.0, 30000.0, "w16_f090_p120B"),
          (200.0, 700.0, "w16_f090_p300A")]


def simulate(path, flares):
    return run_sim(path, seed=5, observation={"duration": DURATION},
                   instrument={"bands": ["f090"], "wafers": ["w16"]},
                   flares={"list": [dict(at_detector=d, at_time=t, t_peak=t, s_peak_mjy=s,
                                         t_rise=0.5) for t, s, d in flares]})


@pytest.fixture(scope="module")
def both(module_tmp):
    """(the noise-only group's state, the flares' truth, the flares' S/N less the noise's)."""
    root = module_tmp("fast_path_model")
    noise, flares = simulate(root / "noise", []), simulate(root / "flares", FLARES)
    steps = yaml.safe_load((CONFIGS / "preprocess_paper.yaml").read_text())
    standard, search = split_pipe(steps["process_pipe"])
    group = Group(noise.obs_ids[0], "w16", "f090")
    prepare_group(noise.context, group, standard, search, root / "group")
    state = GroupState.load(group, root / "group", search)
    ctx = core.Context(str(flares.context))
    aman = ctx.get_obs(flares.obs_ids[0], dets={"wafer_slot": "w16", "bandpass": "f090"})
    Pipeline(standard).run(aman)
    assert list(aman.dets.vals) == list(state.aman.dets.vals)
    diff = np.asarray(aman.transient_snr) - np.asarray(state.snr)
    truth = Table.read(flares.context.parent / "truth" / "flares.ecsv")
    return state, truth, diff


def fast_and_full(state, truth, diff, row):
    """Per window of flare ``row``: (the fast path's injected S/N, the pipeline's)."""
    sigma = fwhm_to_sigma(get_band("f090").fwhm)
    centre, radius = state.footprint
    track, = source_crossings(state.timestamps, state.bore_q, [truth[row]], centre, radius,
                              sigma)
    out = []
    for _, dets, lo, hi, signal in injected_windows(state, track, 0.0, Injection()):
        out.append((filtered_snr(state.model, dets, signal), diff[dets, lo:hi]))
    return out


def slopes(state, truth, diff, row):
    """Per window of flare ``row``: the pipeline's S/N over the fast path's, fitted across
    the window's detectors and samples (``sum(fast full) / sum(fast^2)``)."""
    return [float(np.sum(fast * full) / np.sum(fast * fast))
            for fast, full in fast_and_full(state, truth, diff, row)]


@pytest.mark.parametrize("row", [0, 1, 4])
def test_near_the_threshold_the_fast_path_adds_the_pipelines_snr(both, row):
    """400-1500 mJy at f090, t_r = 0.5 s: 2-9 S/N on the best detector. Measured: 0.994 to
    0.999 of the fast path's S/N. Without the PCA's model 0.92-0.94, and without the PSD's
    own-source loss 0.98 (the 2-10 % and 2 % by which the fast path was optimistic). The
    PSD's cross term with this noise scatters the ratio by a few 0.1 %: 1 % is 3 of those."""
    state, truth, diff = both
    ratios = slopes(state, truth, diff, row)
    assert len(ratios) == 1 and abs(ratios[0] - 1) < 0.01, ratios
    pca, state.pca = state.pca, None       # what the fast path did before it modelled the PCA
    try:
        assert slopes(state, truth, diff, row)[0] < 0.95
    finally:
        state.pca = pca


@pytest.mark.parametrize("row", [2, 3])
def test_bright_flares_keep_the_pipelines_snr_within_the_masks_approximation(both, row):
    """5 and 30 Jy: the PCA's mask hides most of these crossings from the PCA, and the
    fast path decides it on the flare alone, not on the flare plus the noise; the filter's
    second pass estimates their detectors' PSD without them. Measured 0.978 and 0.968 of the
    fast path's S/N: flux and position come from the fit, and such flares are found anyway."""
    state, truth, diff = both
    ratios = slopes(state, truth, diff, row)
    assert len(ratios) == 1 and 0.95 < ratios[0] < 1.01, ratios
