"""The real-or-artefact score in sotodlib's site pipeline: transient_fit with the shipped
model scores every fitted candidate, stores the score in the archive, and a cut on it keeps
bright flares on a real wafer (every imperfection at once) while refusing what it scores low."""
import numpy as np
import pytest
import yaml

from so_transients.campaign.real_wafer import PAPER, flare_list, run_mode, score, simulate_seed
from so_transients.score.model import load_model

pytestmark = pytest.mark.slow

MINUTES = 3.0


@pytest.fixture(scope="module")
def scored(module_tmp):
    root = module_tmp("score_pipeline")
    duration = MINUTES * 60
    sim = simulate_seed(root / "data", 9, duration, flare_list(9, duration, n_bright=4,
                                                                n_faint=0))
    cut = load_model("shipped").figures["test"]["paper/significant"]["0.99"]["cut"]
    cfg = yaml.safe_load(PAPER.read_text())
    fit = next(s for s in cfg["process_pipe"] if s["name"] == "transient_fit")
    fit["calc"].update(score_model="shipped", min_real_score=cut)
    template = root / "paper_scored.yaml"
    template.write_text(yaml.safe_dump(cfg, sort_keys=False))
    every = run_mode(sim, root / "runs", "paper", 0.08, template=template, every=True)
    return sim, every, cut


def test_every_fitted_candidate_is_scored_and_only_those(scored):
    _, every, _ = scored
    fitted = np.asarray(every["fit_ok"], bool)
    s = np.asarray(every["real_score"], float)
    assert fitted.any()
    assert np.all((s[fitted] >= 0) & (s[fitted] <= 1)) and np.isnan(s[~fitted]).all()


def test_the_cut_refuses_what_it_scores_low_and_keeps_the_bright_flares(scored):
    sim, every, cut = scored
    s = np.asarray(every["real_score"], float)
    detected = np.asarray(every["detected"], bool)
    passed = np.asarray(every["pass_score"], bool)
    assert np.array_equal(passed, ~(s < cut))         # NaN (not fitted) passes: no score
    assert not np.any(detected & ~passed)
    rows, unmatched = score(sim, every[detected])
    crossed = [r for r in rows if r["crossings"]]
    assert len(crossed) == 4 and all(r["n_det"] == r["crossings"] for r in crossed), rows
    assert unmatched == 0
