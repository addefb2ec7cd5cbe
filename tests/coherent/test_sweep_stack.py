"""Sweep stacking in transient_find's coherent mode: a slow flare too faint for any single
crossing is found by stacking its crossings, fitted, and given a false-alarm rate."""
from types import SimpleNamespace

import numpy as np
import pytest

from so_transients.coherent.config import CoherentConfig
from so_transients.common import candidates
from so_transients.site.pipeline import apply_overrides
from so_transients.detect.find import FindConfig
from so_transients.coherent.sweep_stack import Crossing, kept, stack

from tests.conftest import load_group, run_imperfect_sim, run_sim, run_steps
from tests.coherent.test_coherent_find import coherent_pipe

pytestmark = pytest.mark.slow   # end to end: simulates and runs the pipeline

ARCMIN = np.pi / 180 / 60
FLARE = {"at_detector": "w16_f090_p100A", "at_time": 300.0, "t_peak": 300.0,
         "s_peak_mjy": 90.0, "t_rise": 600.0}
STACKING = {"transient_find": {"calc": {"stack_window": 300.0}},
            "transient_fit": {"calc": {"min_snr": 3.0}}}


def test_a_stack_is_the_weighted_sum_of_its_crossings():
    crossings = [Crossing(0, 10, 3, 2.0, 80.0, 0.02), Crossing(1, 900, 4, 3.0, 60.0, 0.04)]
    res = stack(crossings)
    # Z = (0.02 x 2 + 0.04 x 3) / sqrt(0.02^2 + 0.04^2); flux weighted by n^2
    assert res["z"] == pytest.approx(0.16 / np.sqrt(0.002))
    assert res["flux"] == pytest.approx((0.0004 * 80 + 0.0016 * 60) / 0.002)
    assert res["flux_err"] == pytest.approx(1 / np.sqrt(0.002))
    assert res["share"] == pytest.approx(0.12 / 0.16)


def test_two_crossings_stack_unless_one_makes_the_sum():
    """A steady source's two crossings (Z 5.2 and 4.8, equal weight) stack to 7.1: kept,
    though the better one makes 52 % of the sum (a share limit of 0.5 let no pair of
    crossings stack); a crossing of four times the other's weight makes 93 % of its stack
    with a faint one: not kept, though the stack beats it."""
    pair = [Crossing(0, 10, 3, 5.2, 100.0, 0.03), Crossing(1, 900, 3, 4.8, 90.0, 0.03)]
    assert kept(stack(pair), pair, CoherentConfig())
    assert not kept(stack(pair), pair, CoherentConfig(stack_max_share=0.5))
    lopsided = [Crossing(0, 10, 3, 5.0, 100.0, 0.04), Crossing(1, 900, 3, 1.5, 30.0, 0.01)]
    res = stack(lopsided)
    assert res["z"] > 5.0 and res["share"] > 0.9 and not kept(res, lopsided, CoherentConfig())


@pytest.fixture(scope="module")
def slow_flare(module_tmp):
    """Ten minutes of w16 at f090 (white noise and glitches) with a 90 mJy flare rising and
    decaying over 600 s: each crossing alone reaches Z of about 4 at best."""
    return run_sim(module_tmp("slow"), seed=44, observation={"duration": 600.0},
                   instrument={"tubes": ["i1"], "wafers": ["w16"], "bands": ["f090"]},
                   atmosphere={"enabled": False}, cmb={"enabled": False},
                   flares={"list": [FLARE]})


def search(sim, overrides):
    """The transient steps (with transient_significance, 5 slides) on the flare's group."""
    aman = load_group(sim, band="f090")
    pipe = apply_overrides([s for s in coherent_pipe() if s["name"] in candidates.STEPS
                            or s["name"] == "transient_filter"], overrides)
    at = [s["name"] for s in pipe].index("transient_fit")
    pipe.insert(at, {"name": "transient_significance", "calc": {"n_slides": 5}})
    run_steps(aman, pipe)
    cands = candidates.from_aman(aman.transient_candidates, candidates.CAND_AXIS)
    truth = sim.flares
    dist = np.hypot((cands["cluster_ra"] - truth["ra"][0]) * np.cos(truth["dec"][0]),
                    cands["cluster_dec"] - truth["dec"][0])
    return cands, dist < 1.0 * ARCMIN, aman


def test_stacking_finds_a_slow_flare_no_crossing_shows(slow_flare):
    single, near_single, _ = search(slow_flare, {"transient_find": {"calc": {}}})
    cands, near, aman = search(slow_flare, STACKING)
    stacks = near & (cands["n_crossings"] > 1)
    assert stacks.sum() == 1
    s = np.flatnonzero(stacks)[0]
    # stacking adds: higher than any single crossing's Z at the flare, found or not
    assert cands["map_z"][s] > np.max(single["map_z"][near_single], initial=0.0)
    assert cands["map_z"][s] >= 4.5 and cands["passed"][s]
    # the fit holds the position on each crossing and combines them: the mean flux over
    # its crossings, within 3 sigma (the flare is linear in time: 90 mJy at 300 s, 0 at
    # 300 s either side)
    t0 = float(aman.timestamps[0])
    t = np.linspace(cands["t_start"][s], cands["t_stop"][s], 5) - t0
    # crossings of the scans that overlap the 300 s window (scans of ~90 s here)
    assert 100.0 < cands["t_stop"][s] - cands["t_start"][s] < 300.0 + 2 * 90.0
    expected = np.mean(90.0 * (1 - np.abs(t - 300.0) / 600.0))
    assert abs(cands["flux"][s] - expected) < 3 * cands["flux_err"][s]
    assert cands["snr_fit"][s] >= 3.0 and cands["detected"][s]
    # its false-alarm rate comes from slid stacks and the sign-inverted maps' stacks: the
    # higher of the two, and the lowest far of all candidates
    assert np.isfinite(cands["far_slides"][s]) and np.isfinite(cands["far_inverted"][s])
    assert cands["far"][s] == max(cands["far_slides"][s], cands["far_inverted"][s])
    assert cands["far"][s] == np.nanmin(cands["far"])
    assert cands["coherent_snr"][s] == pytest.approx(cands["map_z"][s], rel=0.05)


@pytest.fixture(scope="module")
def flare_maps(slow_flare):
    """The slow flare's group as stacking reads it: ``maps`` (every scan's map in units of
    its spread), ``q``, ``t``, ``beam``, and ``seeds``: 400 random positions of the maps
    (``(scan, sample, ra, dec)``) away from the flare."""
    from so_transients.detect.find import group_scans
    from so_transients.common.pointing import boresight_q
    from so_transients.common.scan_geometry import sample_rate
    from so_transients.significance.far import SignificanceConfig, band_background, stack_map
    from so_transients.coherent.sweep_stack import sky_position

    aman = load_group(slow_flare, band="f090")
    run_steps(aman, [s for s in coherent_pipe() if s["name"] == "transient_filter"])
    f = aman.transient_filter
    dets = np.flatnonzero(~np.asarray(f.dead, bool))
    beam = float(np.median(np.asarray(f.beam_sigma)[dets]))
    t = np.asarray(aman.timestamps)
    q = boresight_q(aman)
    scan, _ = group_scans(t, aman.boresight.az, aman.boresight.el, FindConfig())
    maps = []
    band_background(aman.transient_snr, dets, t, q, np.asarray(aman.focal_plane.xi)[dets],
                    np.asarray(aman.focal_plane.eta)[dets], scan,
                    np.asarray(f.sigma_amp)[dets], beam, sample_rate(t),
                    SignificanceConfig(n_slides=1), CoherentConfig().vetoes,
                    lambda s, m, _: maps.append(stack_map(s, m, beam, np.asarray(
                        f.sigma_amp)[dets], np.ones(len(dets), bool), t)))
    rng = np.random.default_rng(0)
    truth = slow_flare.flares
    seeds = []
    for m in rng.choice(maps, 400):
        row, sample = rng.integers(len(m.rows)), m.first + rng.integers(m.z.shape[1])
        ra, dec = sky_position(m.geometry, m.rows[row], q, sample)
        if np.hypot((ra - truth["ra"][0]) * np.cos(dec), dec - truth["dec"][0]) > 10 * ARCMIN:
            seeds.append((m.scan, sample, ra, dec))
    return SimpleNamespace(maps=maps, q=q, t=t, beam=beam, seeds=seeds, aman=aman)


def test_stacked_z_of_noise_has_unit_spread(flare_maps):
    """At fixed positions away from the flare, the stacked Z (not a maximum) is a weighted
    sum of unit-spread values, so it has unit spread too: over ~400 positions, within
    four standard errors of 1 (sqrt(1 / 2n) each)."""
    from so_transients.coherent.sweep_stack import stack_at

    f, z = flare_maps, []
    for scan, sample, ra, dec in f.seeds:
        res = stack_at(f.maps, f.q, ra, dec, f.t[sample] - 150.0, f.t[sample] + 150.0,
                       0.8 * f.beam)
        if res is not None:
            z.append(res["z"])
    z = np.asarray(z)
    assert len(z) > 200
    assert abs(np.std(z) - 1.0) < 4 * np.sqrt(1 / (2 * len(z)))
    assert abs(np.mean(z)) < 4 / np.sqrt(len(z))


def _slid(f, seeds, offsets):
    """:func:`stack_statistics` of ``seeds`` on ``f.maps`` moved by ``offsets``."""
    from so_transients.significance.stack_slides import seed_cells, slid_values, stack_statistics
    cells = seed_cells(f.maps, seeds, f.q, f.t, 0.8 * f.beam, 300.0)
    return stack_statistics(slid_values(f.maps, cells, offsets), cells), cells


def test_a_stack_slide_reads_what_stacking_reads_unmoved(flare_maps):
    """With every offset 0 a slide is the data: each seed's stack is sweep_stack's."""
    from so_transients.coherent.sweep_stack import stack_at
    f = flare_maps
    seeds = f.seeds[:40]
    stats, cells = _slid(f, seeds, np.zeros((1, len(f.maps)), np.int64))
    for k, (ra, dec) in enumerate(zip(cells.ra, cells.dec)):
        t = f.t[next(s[1] for s in seeds if s[2] == ra and s[3] == dec)]
        res = stack_at(f.maps, f.q, ra, dec, t - 150.0, t + 150.0, 0.8 * f.beam)
        assert stats["z"][0, k] == pytest.approx(res["z"], rel=1e-5)
        assert stats["share"][0, k] == pytest.approx(res["share"], rel=1e-5)


def test_crossings_found_at_once_are_those_found_one_by_one(flare_maps):
    """Every map's seeds are placed on it at once (one so3g call): the same crossings as
    placing each seed on each map on its own, from the same focal-plane positions."""
    from so_transients.common.pointing import source_in_focal_plane, sources_in_focal_plane
    from so_transients.coherent.sweep_stack import crossing_of, seed_crossings
    f = flare_maps
    seeds = f.seeds[:60]
    samples = [s[1] for s in seeds]
    xi, eta = sources_in_focal_plane(f.q[samples], [s[2] for s in seeds],
                                     [s[3] for s in seeds])
    for k, (_, sample, ra, dec) in enumerate(seeds):
        one = source_in_focal_plane(f.q[[sample]], ra, dec)
        assert (xi[k], eta[k]) == pytest.approx((one[0][0], one[1][0]), abs=1e-12)
    found = seed_crossings(f.maps, seeds, f.q, f.t, 0.8 * f.beam, 300.0)
    assert sum(len(c) for c in found) > len(seeds)
    for (_, sample, ra, dec), crossings in zip(seeds, found):
        alone = [c for c in (crossing_of(m, f.q, ra, dec, 0.8 * f.beam) for m in f.maps
                             if m.t_hi >= f.t[sample] - 150.0 and m.t_lo <= f.t[sample] + 150.0)
                 if c is not None]
        assert crossings == alone


def test_stack_slides_remove_the_flare_and_keep_the_noise(flare_maps, slow_flare):
    """Slid, the flare's stack (its crossings no longer lined up) falls to the noise: over
    200 slides its mean is the seed's own term (the held crossing) and no more, within four
    standard errors; noise positions' slid stacks keep unit spread and zero mean."""
    from so_transients.significance.stack_slides import slide_offsets
    from so_transients.coherent.sweep_stack import crossing_of, sky_position
    f = flare_maps
    truth = slow_flare.flares
    ra, dec = float(truth["ra"][0]), float(truth["dec"][0])
    sample = int(np.searchsorted(f.t, f.t[0] + 300.0))
    m = min(f.maps, key=lambda m: abs(m.first + m.z.shape[1] // 2 - sample))
    own = crossing_of(m, f.q, ra, dec, 0.8 * f.beam)
    seed = [(m.scan, own.sample, *sky_position(m.geometry, m.rows[own.row], f.q, own.sample))]
    data, _ = _slid(f, seed, np.zeros((1, len(f.maps)), np.int64))
    offsets = slide_offsets(f.maps, 200, 200, np.random.default_rng(1))
    slid, cells = _slid(f, seed, offsets)
    held = own.n * own.z / np.sqrt(np.sum(cells.n**2))
    assert data["z"][0, 0] >= 4.5
    assert abs(slid["z"][:, 0].mean() - held) < 4 / np.sqrt(200)
    noise, cells = _slid(f, f.seeds, offsets[:20])
    z = noise["z"][noise["count"] >= 2]
    assert len(z) > 4000
    # a position's slides share its held crossing (about a third of the variance: three
    # crossings a stack here), so the errors are those of the positions' count, not the
    # values'
    n = len(cells.starts)
    assert abs(np.std(z) - 1.0) < 4 * np.sqrt(1 / (2 * n))
    assert abs(np.mean(z)) < 4 / np.sqrt(n)


def test_stacking_holds_on_imperfect_detectors(tmp_path):
    """16 % dead detectors (NaN), 2 % ten times noisier and 200 glitches per hour, the
    transient steps alone: every Z is finite, the slow flare is stacked, its fit and far are
    finite, and no dead detector is a hit."""
    sim = run_imperfect_sim(tmp_path, {**FLARE, "s_peak_mjy": 110.0}, 600.0)
    cands, near, aman = search(sim, STACKING)
    assert np.all(np.isfinite(cands["map_z"]))
    stacks = np.flatnonzero(near & (cands["n_crossings"] > 1))
    assert len(stacks) == 1
    s = stacks[0]
    assert np.isfinite(cands["far"][s]) and cands["flux"][s] > 0 and cands["snr_fit"][s] > 3
    dead = np.flatnonzero(np.asarray(aman.transient_filter.dead, bool))
    assert len(dead) >= 0.1 * aman.dets.count
    assert not np.isin(np.asarray(aman.transient_hits.det), dead).any()
