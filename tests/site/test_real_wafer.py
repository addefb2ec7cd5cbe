"""A real wafer has every imperfection at once (studies/configs/real_wafer.yaml: dead channels
that still carry jumps and cosmic rays, +-5 Jy readout jumps, 25 % noise scatter, 8 % gain
scatter, time constants, focal-plane errors, a lost channel, a NaN stretch, cosmic rays on
5-40 detectors): through sotodlib's site pipeline in both search modes, on two seeds, every
bright flare is found once, at its flux and position, and nothing else is detected."""
import numpy as np
import pytest

from so_transients.campaign.real_wafer import flare_list, run_mode, score, simulate_seed
from so_transients.site.losses import group_losses

pytestmark = pytest.mark.slow

MINUTES = 4.0


@pytest.fixture(scope="module", params=[3, 4])
def wafer(request, module_tmp):
    seed = request.param
    root = module_tmp(f"real_wafer_{seed}")
    duration = MINUTES * 60
    return root, simulate_seed(root / "data", seed, duration,
                               flare_list(seed, duration, n_bright=4, n_faint=0))


@pytest.fixture(scope="module", params=["paper", "coherent"])
def run(request, wafer):
    root, sim = wafer
    return request.param, sim, run_mode(sim, root / "runs", request.param, max_far=0.08), root


def test_every_bright_flare_once_at_its_flux_and_place_and_nothing_else(run):
    mode, sim, found, _ = run
    rows, unmatched = score(sim, found)
    crossed = [r for r in rows if r["crossings"]]
    assert len(crossed) == 4
    assert all(r["n_det"] == r["crossings"] for r in crossed), (mode, rows)  # found, once each
    ratios = np.array([r["flux_ratio"] for r in crossed])
    # t_r = 10 s: the flux is S_p within 0.5 % during a crossing. The fit's error at S/N ~ 70
    # is 1.5 %, and ideal detectors give -1 +- 6 % at t_r = 15 s (docs/results/table2.md);
    # the bound for a real wafer is 10 %
    assert np.all(np.abs(ratios - 1) < 0.10), (mode, ratios)
    offsets = np.array([r["offset_arcmin"] for r in crossed])
    assert np.all(offsets < 0.2), (mode, offsets)     # the issue's bound; matched within 3'
    assert unmatched == 0, f"{mode}: {unmatched} detections match no flare"


def test_the_archive_says_what_each_group_lost(run):
    mode, sim, _, root = run
    losses = group_losses(root / "runs" / f"{mode}.yaml")
    assert len(losses) == 1
    row = losses[0]
    # 15 % dead channels, one lost channel: every one of them is removed by the standard
    # steps or left out by transient_filter, and no more than a few live ones with them
    dead = int(round(0.15 * row["n_dets"])) + 1
    assert row["n_dets"] - row["used"] >= dead
    assert row["n_dets"] - row["used"] <= dead + 0.02 * row["n_dets"]
    assert row["removed_upstream"] + row["excluded_no_data"] + row["excluded_too_quiet"] \
        + row["excluded_too_noisy"] == row["n_dets"] - row["used"]
