"""A group's health: the effective number of detectors its weights leave."""
import numpy as np
import pytest
from astropy.table import Table
from sotodlib import core

from so_transients.detect.health import health_warnings, weight_health
from so_transients.site.losses import proc_losses, report


def test_lognormal_noise_scatter_leaves_exp_minus_4s2_of_the_detectors():
    rng = np.random.default_rng(0)
    n, s = 20000, 0.25
    sigma = 150 * np.exp(s * rng.standard_normal(n))
    health = weight_health(sigma, np.ones(n, bool))
    # n_eff / n = E[w]^2 / E[w^2] = exp(-4 s^2) for log-normal sigma; its estimate from
    # 20000 draws is good to ~1 %
    assert health["eff_fraction"] == pytest.approx(np.exp(-4 * s**2), rel=0.03)
    assert health_warnings(health) == []


def test_three_channels_weighted_a_thousand_times_too_high_are_reported():
    sigma = np.full(620, 146.0)
    sigma[:3] = [0.1, 0.3, 0.6]
    used = np.ones(620, bool)
    health = weight_health(sigma, used)
    assert health["n_eff"] < 3
    problems = health_warnings(health)
    assert len(problems) == 2 and "effective number of detectors" in problems[0]
    # left out, they no longer weigh anything
    used[:3] = False
    assert weight_health(sigma, used)["n_eff"] == pytest.approx(617)
    assert health_warnings(weight_health(sigma, used)) == []


def test_a_groups_losses_say_when_its_weights_are_unhealthy():
    """What `run` and `catalog` report per group, from the archived transient_filter."""
    ndet = 200
    proc = core.AxisManager(core.LabelAxis("dets", [f"d{i}" for i in range(ndet)]))
    f = core.AxisManager(proc.dets)
    sigma = np.full(ndet, 146.0)
    sigma[:3] = [0.1, 0.3, 0.6]                   # weighed as if a thousand times quieter
    for name, value in (("sigma_amp", sigma), ("excluded", np.zeros(ndet, np.int8)),
                        ("dead", np.zeros(ndet, bool)), ("n_jumps", np.zeros(ndet, int)),
                        ("masked_fraction", np.zeros(ndet, np.float32))):
        f.wrap(name, value, [(0, "dets")])
    proc.wrap("transient_filter", f)
    row = proc_losses(proc)
    assert row["used"] == ndet and row["n_eff"] < 3
    assert "effective number of detectors" in row["health"]
    line = report(Table(rows=[{"obs_id": "obs_1", "group": "w16/f090", **row}]))
    assert "obs_1 w16/f090" in line and "one detector carries 88 % of the weight" in line
