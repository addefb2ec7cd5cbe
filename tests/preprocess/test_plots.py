"""The per-detection figures of ``transient_fit``: named by the step, saying which mode found
the candidate with its ``map_z`` and ``far``, and labelling the contributing detectors as
what ``transient_hits`` holds in each mode."""
import re

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.text import Text
from sotodlib.preprocess import Pipeline

from so_transients.common import candidates
from so_transients.preprocess.plots import detection_figure, detection_name, find_mode

from tests.conftest import load_group

pytestmark = pytest.mark.slow   # simulates and runs the transient steps

FILTER = {"name": "transient_filter", "process": {}, "calc": True, "save": True}
CUTS = {"name": "transient_cuts", "calc": {}, "save": True}
FIT = {"name": "transient_fit", "calc": {}, "save": True, "plot": True}
SIGNIFICANCE = {"name": "transient_significance", "calc": {"n_slides": 5}, "save": True}
PAPER = [FILTER, {"name": "transient_find", "calc": {"mode": "paper"}, "save": True}, CUTS,
         FIT]
COHERENT = [FILTER, {"name": "transient_find", "calc": {"mode": "coherent"}, "save": True},
            CUTS, SIGNIFICANCE, FIT]


def run(dataset, steps, plot_dir):
    """The steps through sotodlib's Pipeline (which calls ``plot`` with its file name)."""
    aman = load_group(dataset)
    Pipeline(steps, plot_dir=str(plot_dir)).run(aman)
    return aman


@pytest.fixture(scope="module")
def runs(bright_source_dataset, module_tmp):
    """The bright flare's group searched in each mode (coherent: with transient_significance
    inserted before transient_fit, which moves the fit's step index)."""
    out = {}
    for mode, steps in (("paper", PAPER), ("coherent", COHERENT)):
        plot_dir = module_tmp(f"plots_{mode}")
        out[mode] = run(bright_source_dataset, steps, plot_dir), plot_dir
    return out


def detected(aman):
    return np.flatnonzero(np.asarray(aman.transient_candidates.detected, bool))


def figure_text(aman, cand):
    """Every text of the detection's figure (titles, axis and colour-bar labels)."""
    fig = detection_figure(aman, cand)
    try:
        return "\n".join(t.get_text() for t in fig.findobj(Text))
    finally:
        plt.close(fig)


@pytest.mark.parametrize("mode", ["paper", "coherent"])
def test_pngs_are_named_by_step_in_the_pipeline_folder(runs, mode):
    aman, plot_dir = runs[mode]
    assert len(detected(aman)) >= 1
    folder = plot_dir / str(aman.timestamps[0])[:5] / aman.obs_info.obs_id
    expected = {f"transient_fit_{detection_name(aman, c)}.png" for c in detected(aman)}
    assert {p.name for p in folder.iterdir()} == expected
    assert not any(re.match(r"\d", p.name) for p in plot_dir.rglob("*.png"))


def test_the_coherent_figure_shows_the_mode_map_z_and_far(runs):
    aman, _ = runs["coherent"]
    cands = aman.transient_candidates
    for c in detected(aman):
        assert find_mode(aman, c) == "coherent"
        text = figure_text(aman, c)
        assert "transient_find mode: coherent" in text
        assert f"map_z {cands.map_z[c]:.2f}" in text
        assert np.isfinite(cands.far[c]) and f"far {cands.far[c]:.3g} per wafer-band-hour" in text


def test_the_paper_figure_says_what_is_missing_and_why(runs):
    aman, _ = runs["paper"]
    assert "far" not in aman.transient_candidates._fields     # no transient_significance
    for c in detected(aman):
        assert find_mode(aman, c) == "paper"
        text = figure_text(aman, c)
        assert "transient_find mode: paper" in text
        assert "map_z n/a (paper mode)" in text
        assert "far n/a (no transient_significance)" in text


def hit_snr(aman, cand):
    hits = aman.transient_hits
    return np.asarray(hits.snr)[np.asarray(hits.cand) == cand]


def test_paper_mode_labels_its_detectors_by_the_threshold_they_passed(runs):
    aman, _ = runs["paper"]
    for c in detected(aman):
        n = len(np.unique(np.asarray(aman.transient_hits.det)[
            np.asarray(aman.transient_hits.cand) == c]))
        text = figure_text(aman, c)
        assert f"{n} detectors with clustered samples\nat or above the S/N threshold" in text
        assert hit_snr(aman, c).min() >= 3.0       # the label holds: the default threshold


def test_coherent_mode_does_not_claim_an_snr_threshold(runs):
    """The coherent sum's detectors include faint and negative ones: the figure says so."""
    aman, _ = runs["coherent"]
    snr = np.concatenate([hit_snr(aman, c) for c in detected(aman)])
    assert snr.min() < 3.0          # a threshold label would be false on this very figure
    for c in detected(aman):
        text = figure_text(aman, c)
        assert "threshold" not in text
        assert "detectors in the coherent sum\nnear the peak, of either sign" in text
        assert "S/N where the position crosses the detector" in text


def test_the_mode_is_read_from_the_find_steps_output(runs):
    """``map_z`` (stored by transient_find) is finite exactly in coherent mode."""
    for mode, (aman, _) in runs.items():
        rows = candidates.from_aman(aman.transient_candidates, candidates.CAND_AXIS)
        assert np.isfinite(rows["map_z"]).all() == (mode == "coherent")
        assert np.isnan(rows["map_z"]).all() == (mode == "paper")
