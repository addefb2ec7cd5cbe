"""The quick campaign, run as a user runs it: ``so-transients campaign`` in a subprocess."""
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table

ROOT = Path(__file__).resolve().parents[2]
QUICK = ROOT / "studies" / "configs" / "campaign_quick.yaml"


def campaign(out, *extra):
    env = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="passive")
    cmd = [sys.executable, "-m", "so_transients.cli", "campaign", str(QUICK), "-o", str(out),
           "--nproc", "2", "-q", *extra]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("campaign") / "quick"
    run = campaign(out)
    assert run.returncode == 0, run.stderr[-3000:]
    return out, run


def test_every_output_is_written(quick):
    out, run = quick
    results = out / "results"
    for name in ("efficiency.ecsv", "thresholds.ecsv", "thresholds.md", "flux_residuals.ecsv",
                 "pointing.ecsv", "false_positives.ecsv", "full_check.ecsv", "flares.ecsv",
                 "efficiency.png", "flux_residuals.png", "pointing.png"):
        assert (results / name).stat().st_size > 0, name
    assert "| 0.5 |" in run.stdout and "| 400 | 550 | 800 |" in run.stdout   # paper's Table 2
    false = Table.read(results / "false_positives.ecsv")
    assert str(false["rate_noise"].unit) == "1 / h" and false["hours"][0] == pytest.approx(1 / 6, rel=1e-3)
    # the per-group searches (run in the pool while the next group was prepared) all finished
    groups = sorted((out / "noise" / "groups").iterdir())
    counts = [json.loads((g / "false_positives.json").read_text()) for g in groups]
    assert all(c["inverted"] and c["stamp"] == (g / "digest.txt").read_text()
               for c, g in zip(counts, groups))
    assert false["n_noise"].sum() == sum(len(Table.read(g / "false_noise.ecsv")) for g in groups)
    assert false["n_inverted"].sum() == sum(c["n_false_inverted"] for c in counts)


def test_a_false_alarm_budget_keeps_only_detections_below_it(quick):
    """``far_budget`` in paper mode: each group's background of 100 slides, every detection's
    coherent_snr, and a flare detected at the budget only where the fit detected it."""
    out, _ = quick
    results = out / "results"
    budget = Table.read(results / "far_budget.ecsv")
    assert set(budget["band"]) == {"f090", "f220"} and set(budget["statistic"]) == {"coherent_snr"}
    # the slides search whole scans: at least n_slides times the data's live time
    assert np.all(budget["slide_hours"] >= 100 * budget["data_hours"])
    assert np.all(np.isfinite(budget["z_budget"])) and np.all(budget["z_budget"] > 3)
    assert all((g / "background.npz").exists() for g in (out / "noise" / "groups").iterdir())
    res = Table.read(results / "flux_residuals.ecsv")
    assert np.mean(np.isfinite(res["coherent_snr"])) > 0.9
    key = lambda t: [(str(b), float(r), float(p)) for b, r, p in
                     zip(t["band"], t["t_rise"], t["s_peak"])]
    eff, at_budget = (Table.read(results / f"{name}.ecsv")
                      for name in ("efficiency", "efficiency_far"))
    assert key(eff) == key(at_budget)
    assert np.all(at_budget["detected"] <= eff["detected"])
    bright = (eff["band"] == "f090") & (eff["s_peak"] == 1200)
    # a 1.2 Jy flare's Z (beyond 15) is far above the budget's: detected all the same
    assert np.all(at_budget["detected"][bright] >= 0.8 * eff["detected"][bright])
    # the noise-only search gave its candidates their Z too (the budget's check counts them)
    fitted = Table.read(results / "fitted_noise.ecsv")
    assert np.mean(np.isfinite(fitted["coherent_snr"])) > 0.9


def test_efficiency_rises_with_peak_flux_within_errors(quick):
    eff = Table.read(quick[0] / "results" / "efficiency.ecsv")
    assert set(eff["injected"]) == {20}
    assert set(eff["band"]) == {"f090", "f220"}          # an MF and a UHF tube
    for band, t_rise in set(zip(eff["band"], eff["t_rise"])):
        rows = eff[(eff["band"] == band) & (eff["t_rise"] == t_rise)]
        rows.sort("s_peak")
        e = np.asarray(rows["efficiency"])
        sigma = (np.asarray(rows["eff_hi"]) - np.asarray(rows["eff_lo"])) / 2
        for i in range(len(rows)):
            for j in range(i + 1, len(rows)):
                # one-sided 3 sigma: ~0.1 % chance per pair of a false failure
                assert e[j] >= e[i] - 3 * np.hypot(sigma[i], sigma[j]), (band, t_rise, i, j)
        assert e[-1] - e[0] > 3 * np.hypot(sigma[0], sigma[-1])   # it really rises


def test_fast_path_agrees_with_the_full_site_pipeline(quick):
    check = Table.read(quick[0] / "results" / "full_check.ecsv")
    assert len(check) == 1 and check["n"][0] == 15
    assert abs(check["z"][0]) < 3
    # the same noise and flares: most flares get the same verdict from both paths
    assert check["agree"][0] >= 0.7 * check["n"][0]


def test_detections_carry_flux_and_pointing_truth(quick):
    res = Table.read(quick[0] / "results" / "flux_residuals.ecsv")
    assert len(res) > 0 and np.all(res["offset"] <= 0.5 * np.pi / 180 / 60)
    bright = res[(res["s_peak"] == 1200) & (res["t_rise"] == 5)]
    # S/N ~ 30 in the fit: the flux at the detection time is recovered to within a few errors
    pull = (bright["flux"] - bright["flux_true"]) / bright["flux_err"]
    assert abs(np.median(pull)) < 3


def test_an_interrupted_campaign_resumes_and_refuses_another_config(quick, tmp_path):
    out, _ = quick
    units = sorted((out / "units").glob("*.flares.ecsv"))
    kept = {p: p.stat().st_mtime_ns for p in units[1:]}
    before = Table.read(units[0])
    units[0].unlink()
    rerun = campaign(out)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert all(p.stat().st_mtime_ns == t for p, t in kept.items())    # not redone
    again = Table.read(units[0])
    assert np.array_equal(again["detected"], before["detected"])        # same seed, same result
    changed = tmp_path / "changed.yaml"
    changed.write_text(QUICK.read_text().replace("n_flares: 20", "n_flares: 21"))
    env = dict(os.environ, OMP_NUM_THREADS="1")
    refused = subprocess.run([sys.executable, "-m", "so_transients.cli", "campaign", str(changed),
                              "-o", str(out), "-q"], env=env, capture_output=True, text=True)
    assert refused.returncode == 2 and "another config" in refused.stderr


MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")


@pytest.mark.skipif(not (MPIEXEC and importlib.util.find_spec("mpi4py")),
                    reason="needs an MPI runtime and mpi4py (pip install '.[mpi]')")
def test_units_run_on_mpi_ranks_give_the_same_results(quick, tmp_path):
    """``mpiexec -n 3`` (rank 0 dispatching to two worker ranks through sotodlib's
    get_exec_env) redoes the t_r = 5 s units, and the full check's site pipeline runs as its
    own job from rank 0; every result equals the process pool's."""
    out = tmp_path / "mpi"
    shutil.copytree(quick[0], out)
    redo = list((out / "units").glob("f090_tr5_*"))
    assert redo
    for path in redo:
        path.unlink()
    env = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="passive")
    cmd = [MPIEXEC, "-n", "3", sys.executable, "-m", "so_transients.cli", "campaign", str(QUICK),
           "-o", str(out), "--nproc", "2", "-q"]
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)
    assert run.returncode == 0, run.stderr[-3000:]
    assert all(path.exists() for path in redo)
    for name in ("efficiency.ecsv", "full_check.ecsv"):
        ours, pool = (Table.read(folder / "results" / name).pformat(max_lines=-1, max_width=-1)
                      for folder in (out, quick[0]))
        assert ours == pool, name


def test_a_prepared_groups_false_alarm_background(quick):
    """The coherent mode's background on a prepared noise-only group: the searched scans'
    data and their slides, counted from the floor, in units of the data map's spread."""
    from so_transients.campaign.config import load_campaign
    from so_transients.campaign.far_budget import group_background
    from so_transients.campaign.noise import GroupState, campaign_groups
    from so_transients.significance.far import SignificanceConfig

    cfg = load_campaign(QUICK)
    _, search = cfg.pipeline_steps()
    group = next(g for g in campaign_groups(cfg) if g.band == "f090")
    state = GroupState.load(group, quick[0] / "noise" / "groups" / group.label, search)
    # slides counted from Z = 3, as the inverted data (the default floor for slides is 4.5)
    b = group_background(state, search, SignificanceConfig(n_slides=3, slide_floor=3.0))
    duration = 600.0 / 3600
    # the constant-speed part of the 10 minutes, less the crossings cut by a scan's ends
    assert 0.5 * duration < b.data_hours < duration
    # the slides search whole scans, three times over
    assert 3 * b.data_hours <= b.slide_hours < 3 * 1.3 * b.data_hours
    assert b.slides.min() >= b.floor and b.inverted.min() >= b.floor and b.slide_floor == 3.0
    assert 1.0 < b.scale < 1.6      # residual atmosphere widens the data's Z (1.19 measured)
    # about a thousand maxima per hour above Z = 3 at f090 (the far calibration's 30 minutes)
    assert 100 < len(b.slides) / b.slide_hours < 10_000
    assert b.far(3.0)["far"][0] > b.far(5.0)["far"][0]
