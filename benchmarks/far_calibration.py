"""Benchmark: is the time-slide background a fair model of the data's own noise?

    python benchmarks/far_calibration.py                 # 30 minutes of w16 at f090
    python benchmarks/far_calibration.py --minutes 60 --slides 20 --plot far.png

Simulates a noise-only observation (atmosphere, CMB, white noise, glitches), runs the shipped
standard steps and ``transient_filter``, then for every scan computes the coherent statistic
Z of every position (:mod:`so_transients.coherent`) on the data and on ``--slides`` time
slides, as ``transient_significance`` does. If the slides model the data's noise, the number
of the data map's local maxima with Z >= z equals far(z) x the data's live time for every z
(Poisson errors); the sign-inverted data's maxima (noise with every correlation kept, no
source) are a second model over the same live time. Each map is in units of its own measured spread, as
``transient_significance`` normalizes them: time slides remove the correlation of
neighbouring detectors, so the data's spread is wider than the slides'. Prints the
comparison and both spreads, and optionally plots it.
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
from so_transients import pointing  # noqa: E402
from so_transients.coherent import (false_alarm_rate, largest_share,  # noqa: E402
                                    local_maxima, measured_scale)
from so_transients.find import FindConfig, group_scans  # noqa: E402
from so_transients.scan_geometry import sample_rate  # noqa: E402
from so_transients.significance import (SignificanceConfig, scan_geometry,  # noqa: E402
                                        scan_maps)
from so_transients.sim.config import SimConfig  # noqa: E402
from so_transients.sim.simulate import simulate  # noqa: E402

CONFIG = os.path.join(os.path.dirname(__file__), "..", "configs", "preprocess_transients.yaml")


def filtered_group(minutes, tmp, seed):
    sim = simulate(SimConfig.from_dict({
        "output": tmp, "seed": seed, "observation": {"duration": 60.0 * minutes},
        "instrument": {"tubes": ["i1"], "wafers": ["w16"], "bands": ["f090"]},
        "glitches": {"enabled": True}}), progress=False)
    ctx = core.Context(str(sim.context))
    aman = ctx.get_obs(sim.obs_ids[0], dets={"wafer_slot": "w16", "bandpass": "f090"})
    with open(CONFIG) as f:
        steps = yaml.safe_load(f)["process_pipe"]
    upto = [s["name"] for s in steps].index("transient_filter") + 1
    Pipeline(steps[:upto], logger=logging.getLogger("far_calibration")).run(aman)
    return aman


def maps_of(aman, cfg):
    t, az, el = np.asarray(aman.timestamps), aman.boresight.az, aman.boresight.el
    scan, _ = group_scans(t, az, el, FindConfig())
    f = aman.transient_filter
    live = ~np.asarray(f.dead, bool)
    dets = np.flatnonzero(live)
    q = pointing.boresight_q(aman)
    xi, eta = np.asarray(aman.focal_plane.xi)[dets], np.asarray(aman.focal_plane.eta)[dets]
    sigma = np.asarray(f.sigma_amp)[dets]
    beam = float(np.median(np.asarray(f.beam_sigma)[dets]))
    rng = np.random.default_rng(cfg.seed)
    out, snrs = [], []
    for s in np.unique(scan[scan >= 0]):
        samples = np.flatnonzero(scan == s)
        geometry = scan_geometry(t, q, xi, eta, samples, sample_rate(t))
        snr = np.asarray(aman.transient_snr[dets, samples[0]:samples[-1] + 1])
        out.append(scan_maps(snr, geometry, beam, sigma, np.ones(len(dets), bool),
                             samples[0], cfg, rng))
        snrs.append(snr)
    return out, beam, snrs, [sigma] * len(out)


def maxima(maps, snrs, sigmas, beam, scale, cfg, sign):
    """Z of the local maxima of ``sign`` x each data map (-1: the sign-inverted data, whose
    maxima are noise with all its correlations and no source), in units of ``scale``; as
    for the background, maxima one detector makes are left out."""
    out = []
    for m, snr, sigma in zip(maps, snrs, sigmas):
        window = max(1, int(m.geometry.sample_rate * beam / m.geometry.speed))
        z = sign * m.z
        r, s = local_maxima(z, 2.0 * scale, window)
        keep = largest_share(sign * snr, m.geometry, m.rows, beam, sigma,
                             np.ones(len(sigma), bool), r, s) <= cfg.max_single_share
        out.extend(z[r[keep], s[keep]] / scale)
    return np.asarray(out)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--slides", type=int, default=20)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--plot", metavar="PNG")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        aman = filtered_group(args.minutes, tmp, args.seed)
    print(f"simulated and filtered {aman.dets.count} x {aman.samps.count} in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    cfg = SignificanceConfig(n_slides=args.slides, background_floor=2.0)
    t1 = time.perf_counter()
    maps, beam, snrs, sigmas = maps_of(aman, cfg)
    elapsed = time.perf_counter() - t1
    scale = float(np.median([s for m in maps for s in m.slide_scale]))
    data_scale = float(np.median([measured_scale(m.z) for m in maps]))
    background = np.concatenate([np.asarray(m.background) for m in maps]) / scale
    live_bg = sum(m.live_s for m in maps) / 3600.0
    live_data = live_bg / args.slides
    data_max = maxima(maps, snrs, sigmas, beam, data_scale, cfg, sign=1)
    inverted_max = maxima(maps, snrs, sigmas, beam, data_scale, cfg, sign=-1)
    print(f"maps: {elapsed:.0f} s for {len(maps)} scans x (1 + {args.slides} slides); "
          f"Z spread: data {data_scale:.3f}, slides {scale:.3f} (ratio "
          f"{data_scale / scale:.3f}); live time: data {live_data:.2f} h, background "
          f"{live_bg:.1f} h")
    print(f"\n{'Z >=':>6}{'data maxima':>13}{'inverted data':>15}{'expected (slides)':>19}"
          f"{'pull':>7}")
    levels = np.arange(3.0, 7.01, 0.5)
    expected = false_alarm_rate(levels, background, live_bg) * live_data
    observed = np.array([np.sum(data_max >= z) for z in levels])
    inverted = np.array([np.sum(inverted_max >= z) for z in levels])
    for z, n, i, e in zip(levels, observed, inverted, expected):
        print(f"{z:>6.1f}{n:>13d}{i:>15d}{e:>19.1f}{(n - e) / np.sqrt(max(e, 1)):>7.1f}")
    if args.plot:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.errorbar(levels, observed, np.sqrt(observed), fmt="o",
                    label="data: local maxima of Z")
        ax.plot(levels, np.where(inverted > 0, inverted, np.nan), "s", mfc="none",
                label="sign-inverted data (no source, same correlations)")
        ax.plot(levels, expected, "-", label="far(Z) x live time (time slides)")
        ax.set_yscale("log")
        ax.set_xlabel("Z")
        ax.set_ylabel("number with statistic >= Z")
        ax.set_title(f"noise-only f090, {args.minutes:.0f} min of w16, {args.slides} slides")
        ax.legend()
        fig.tight_layout()
        fig.savefig(args.plot, dpi=110)
        print(f"figure: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
