"""Dead channels with a busy readout (studies/configs/real_wafer_busy_readout.yaml: jumps,
4-12 each, on a fifth of the channels, cosmic rays at 1200 an hour) have a white-band level a
third of a live detector's and an amplitude spread a thousand times smaller. Weighted by
the latter, three of them carried 99 % of the wafer's weight and bright flares came out 1-2'
off at a fifth of their flux, with fitted S/N above 40. Through sotodlib's site pipeline now:
the group's weight is spread over its live detectors, every bright flare is found at its
flux and place, and nothing is detected in the wrong place."""
import numpy as np
import pytest

from so_transients.campaign.real_wafer import (
    ROOT, flare_list, mislocated, run_mode, score, simulate_seed
)
from so_transients.site.losses import group_losses

pytestmark = pytest.mark.slow

MINUTES = 4.0
CONFIG = ROOT / "studies" / "configs" / "real_wafer_busy_readout.yaml"


@pytest.fixture(scope="module")
def run(module_tmp):
    root = module_tmp("busy_readout")
    duration = MINUTES * 60
    sim = simulate_seed(root / "data", 1, duration, flare_list(1, duration, n_bright=6, n_faint=0),
                        CONFIG)
    return sim, run_mode(sim, root / "runs", "coherent", max_far=0.08), root


def test_no_channel_carries_a_weight_its_selection_did_not_vouch_for(run):
    _, _, root = run
    row = group_losses(root / "runs" / "coherent.yaml")[0]
    # the live detectors' noise scatters by 25 % (log-normal): n_eff / used = exp(-4 s^2)
    # = 0.78; three dead channels left in made it 1.7 of 734
    assert row["eff_fraction"] > 0.6, dict(zip(row.colnames, row))
    assert row["health"] == ""
    assert row["excluded_non_gaussian"] + row["excluded_too_quiet"] >= 1


def test_every_bright_flare_at_its_flux_and_place_and_none_elsewhere(run):
    sim, found, _ = run
    rows, unmatched = score(sim, found)
    crossed = [r for r in rows if r["crossings"]]
    assert len(crossed) >= 5
    assert all(r["n_det"] == r["crossings"] for r in crossed), rows
    ratios = np.array([r["flux_ratio"] for r in crossed])
    assert np.all(np.abs(ratios - 1) < 0.10), ratios
    assert np.all(np.array([r["offset_arcmin"] for r in crossed]) < 0.2)
    assert unmatched == 0 and mislocated(sim, found) == 0
