"""Benchmark: what sweep stacking adds for slow flares, at a false-alarm budget.

    python studies/stack_gain.py                       # 30 min of w16 at f090, t_r = 300 s
    python studies/stack_gain.py --flux 60 90 120 --n 8 --minutes 30

The campaign's fast path searches a window around each injected crossing, so it cannot
measure sweep stacking. This simulates whole observations instead (atmosphere, CMB, white
noise, glitches; one per peak flux, ``--n`` flares with t_r = t_d = ``--t-rise`` placed on a
random detector at their peak), runs the shipped standard steps and the transient steps in
coherent mode with ``stack_window`` and ``transient_significance``, and counts, for each
flux, the flares with a candidate within 1' whose ``far`` is within ``--budget`` (per
wafer-band-hour; the paper's rate by default): by single crossings alone, and with stacks.
Candidates within the budget that match no flare are the false ones. Prints a table.

``--noise-only K`` checks the stacks' background instead, on K observations without flares:
is a stack of the sign-inverted maps, or of the maps slid against each other
(``transient_significance``'s two backgrounds of stacked candidates), as likely as a stack
of the data? It counts, over the same hours, the data's stacked candidates (and those
passing the cuts), the inverted maps' stacks and the slid stacks (``--slides`` slides, per
data hour) of each observation (as the step computes them) at Z >= z; then gives every data
stack its ``far`` from the backgrounds of all K observations pooled and from its own
observation's alone (the step's ``far``), and counts those with ``far <= x`` against ``x``
times the hours searched (stacks exist only from ``coherent_threshold`` up, so the count
stops growing at the ``far`` of that Z, printed).
"""
import argparse
import logging
import os
import sys
import tempfile
import time

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import numpy as np  # noqa: E402
import yaml  # noqa: E402
from sotodlib import core  # noqa: E402
from sotodlib.preprocess import Pipeline  # noqa: E402

import so_transients  # noqa: E402,F401  registers the steps and the loader
from so_transients.coherent.config import CoherentConfig  # noqa: E402
from so_transients.common import candidates, pointing  # noqa: E402
from so_transients.common.angles import ARCMIN, sky_separation  # noqa: E402
from so_transients.detect.find import SCAN_FIELD  # noqa: E402
from so_transients.common.scan_geometry import sample_rate  # noqa: E402
from so_transients.significance.far import Background, SignificanceConfig, band_background
from so_transients.site.pipeline import PAPER, apply_overrides  # noqa: E402
from so_transients.sim.config import SimConfig  # noqa: E402
from so_transients.sim.simulate import simulate  # noqa: E402


def pipe(window, n_slides=20):
    """The shipped steps, transient_find in coherent mode with sweep stacking, the fit cut
    at S/N 3 (the budget decides), and transient_significance before the fit."""
    steps = apply_overrides(yaml.safe_load(PAPER.read_text())["process_pipe"],
                            {"transient_find": {"calc": {"mode": "coherent",
                                                         "stack_window": window}},
                             "transient_fit": {"calc": {"min_snr": 3.0}}})
    at = [s["name"] for s in steps].index("transient_fit")
    steps.insert(at, {"name": "transient_significance", "calc": {"n_slides": n_slides}})
    return steps


def search(flux, args, tmp, seed=None, n=None):
    """Candidates of one simulated observation with ``n`` (default ``args.n``) flares of peak
    ``flux``, the flares' truth and the searched group."""
    sim = simulate(SimConfig.from_dict({
        "output": tmp, "seed": args.seed + int(flux) if seed is None else seed,
        "observation": {"duration": 60.0 * args.minutes},
        "instrument": {"tubes": ["i1"], "wafers": ["w16"], "bands": ["f090"]},
        "glitches": {"enabled": True},
        "flares": {"n": args.n if n is None else n, "s_peak_mjy": [max(flux, 1.0)] * 2,
                   "t_rise": [args.t_rise, args.t_rise]}}), progress=False)
    ctx = core.Context(str(sim.context))
    aman = ctx.get_obs(sim.obs_ids[0], dets={"wafer_slot": "w16", "bandpass": "f090"})
    Pipeline(pipe(args.window, args.slides), logger=logging.getLogger("stack_gain")).run(aman)
    return (candidates.from_aman(aman.transient_candidates, candidates.CAND_AXIS), sim.flares,
            aman)


def count(cands, flares, budget, stacks):
    """(flares with a candidate within 1' inside the budget, candidates inside it that match
    no flare), with the stacks (``n_crossings`` > 1) or by single crossings alone."""
    within = ((np.nan_to_num(cands["far"], nan=np.inf) <= budget)
              & np.asarray(cands["passed"], bool))
    if not stacks:
        within &= cands["n_crossings"] == 1
    near = sky_separation(cands["cluster_ra"][:, None], cands["cluster_dec"][:, None],
                          np.asarray(flares["ra"])[None], np.asarray(flares["dec"])[None]) \
        <= 1.0 * ARCMIN
    return int(np.sum(np.any(near[within], axis=0))), int(np.sum(within & ~near.any(axis=1)))


def stack_background(aman, window, n_slides):
    """The :class:`Background` of a searched group's stacks (the sign-inverted maps' and
    ``n_slides`` slides'), as ``transient_significance`` computes it."""
    f = aman.transient_filter
    dets = np.flatnonzero(~np.asarray(f.dead, bool))
    t = np.asarray(aman.timestamps)
    xi, eta = np.asarray(aman.focal_plane.xi), np.asarray(aman.focal_plane.eta)
    background, _ = band_background(
        aman.transient_snr, dets, t, pointing.boresight_q(aman), xi[dets], eta[dets],
        np.asarray(aman[SCAN_FIELD]), np.asarray(f.sigma_amp)[dets],
        float(np.median(np.asarray(f.beam_sigma)[dets])), sample_rate(t),
        SignificanceConfig(n_slides=n_slides), CoherentConfig().vetoes,
        stacking=CoherentConfig(stack_window=window).stacking)
    return background


def noise_only(args):
    """The stacks' background on ``args.noise_only`` observations without flares."""
    z, passed, own_far, inverted, slid, hours, slid_hours = [], [], [], [], [], 0.0, 0.0
    start = time.perf_counter()
    for k in range(args.noise_only):
        with tempfile.TemporaryDirectory() as tmp:
            cands, _, aman = search(0.0, args, tmp, seed=args.seed + 1000 + k, n=0)
            b = stack_background(aman, args.window, args.slides)
        stacked = cands["n_crossings"] > 1
        z.extend(np.asarray(cands["coherent_snr"], float)[stacked])
        passed.extend(np.asarray(cands["passed"], bool)[stacked])
        own_far.extend(np.asarray(cands["far"], float)[stacked])
        inverted.extend(b.stacks)
        slid.extend(b.stack_slides)
        hours += b.data_hours
        slid_hours += b.stack_slide_hours
        print(f"observation {k}: {stacked.sum()} stacks, {len(b.stacks)} inverted stacks from "
              f"Z = 3 and {len(b.stack_slides)} slid stacks from Z = {b.slide_floor:g} in "
              f"{b.data_hours:.3f} h ({(time.perf_counter() - start) / 60:.1f} min)",
              flush=True)
    z, passed = np.asarray(z), np.asarray(passed)
    inverted, slid = np.asarray(inverted), np.asarray(slid)
    per_hour = hours / slid_hours if slid_hours else np.nan
    print(f"\n{'Z >=':>6}{'data stacks':>13}{'passing cuts':>14}{'inverted stacks':>17}"
          f"{'pull':>7}{'slid stacks':>13}{'x hours/slid':>14}{'pull':>7}")
    for level in (4.5, 5.0, 5.5, 6.0, 6.5):
        n, m, s = (int(np.sum(v >= level)) for v in (z, inverted, slid))
        pull = (n - m) / np.sqrt(n + m) if n + m else 0.0
        # the slid count scaled to the data's hours has variance s x per_hour^2
        scaled = s * per_hour
        pull_slid = (n - scaled) / np.sqrt(max(n, 1) + s * per_hour**2)
        print(f"{level:>6.1f}{n:>13d}{int(np.sum(passed & (z >= level))):>14d}{m:>17d}"
              f"{pull:>7.1f}{s:>13d}{scaled:>14.2f}{pull_slid:>7.1f}")
    pooled = Background(np.zeros(0), 0.0, np.zeros(0), hours, stacks=inverted,
                        stack_slides=slid, stack_slide_hours=slid_hours,
                        slide_floor=SignificanceConfig.slide_floor)
    far = pooled.stack_far(z)["far"]
    print(f"\n{'x (1/h)':>9}{'far <= x (pooled)':>19}{'(the step)':>12}{'x T':>8}")
    for x in (0.3, 1.0, 3.0, 10.0, 30.0):
        print(f"{x:>9g}{int(np.sum(far <= x)):>19d}{int(np.sum(np.asarray(own_far) <= x)):>12d}"
              f"{x * hours:>8.2f}")
    print(f"\n{hours:.2f} h searched of w16 at f090 without flares; stack_window "
          f"{args.window:g} s. Pooled, a stack at Z = 4.5 (the threshold) has far "
          f"{pooled.stack_far(4.5)['far'][0]:.2g} per wafer-band-hour: the counts stop growing there.")
    return 0


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flux", type=float, nargs="+", default=[60.0, 90.0, 120.0],
                        help="peak fluxes (mJy), one observation each")
    parser.add_argument("--n", type=int, default=8, help="flares per observation")
    parser.add_argument("--t-rise", type=float, default=300.0, help="s, rise = decay time")
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--window", type=float, default=300.0, help="stack_window, s")
    parser.add_argument("--budget", type=float, default=2 / 24,
                        help="max far per wafer-band-hour (default: the paper's rate)")
    parser.add_argument("--seed", type=int, default=50)
    parser.add_argument("--slides", type=int, default=20,
                        help="transient_significance's n_slides (slid stacks per data stack)")
    parser.add_argument("--noise-only", type=int, default=0, metavar="K",
                        help="check the stacks' far on K observations without flares instead")
    args = parser.parse_args(argv)
    if args.noise_only:
        return noise_only(args)
    print(f"{'S_p (mJy)':>10}{'flares':>8}{'single':>8}{'stacked':>9}"
          f"{'false single':>14}{'false stacked':>15}{'min':>6}")
    for flux in args.flux:
        start = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            cands, flares, _ = search(flux, args, tmp)
        single, false_single = count(cands, flares, args.budget, stacks=False)
        both, false_both = count(cands, flares, args.budget, stacks=True)
        print(f"{flux:>10.0f}{len(flares):>8d}{single:>8d}{both:>9d}{false_single:>14d}"
              f"{false_both:>15d}{(time.perf_counter() - start) / 60:>6.1f}", flush=True)
    print(f"\nfar budget {args.budget:.3f} per wafer-band-hour; {args.minutes:g} min of w16 at "
          f"f090 per flux; t_r = {args.t_rise:g} s; stack_window {args.window:g} s. 'stacked'"
          f" counts flares found by a stack or a single crossing.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
