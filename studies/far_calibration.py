"""Benchmark: is the time-slide background a fair model of the data's own noise?

    python studies/far_calibration.py                 # 30 minutes of w16 at f090
    python studies/far_calibration.py --minutes 60 --slides 20 --plot far.png
    python studies/far_calibration.py --slide-groups 0   # each detector slid on its own
    python studies/far_calibration.py --no-glitches  # without glitches (failing-test tail)

Simulates a noise-only observation (atmosphere, CMB, white noise, glitches), runs the shipped
standard steps and ``transient_filter``, then for every scan computes the coherent statistic
Z of every position (:mod:`so_transients.coherent.statistic`) on the data and on ``--slides`` time
slides, as ``transient_significance`` does. If the slides model the data's noise, the number
of the data map's local maxima with Z >= z equals far(z) x the data's live time for every z
(Poisson errors); the sign-inverted data's maxima (noise with every correlation kept, no
source) are a second model over the same live time. The data's maxima are counted less
those the coherent mode's glitch vetoes remove, and the backgrounds' less those failing its
chi-squared test, as ``transient_significance`` ranks a candidate that passes it. Each map
is in units of its own measured spread, as ``transient_significance`` normalizes them:
time slides remove the correlation of
neighbouring detectors, so the data's spread is wider than the slides'. Prints the
comparison and both spreads; then gives every data maximum its ``far`` as the step gives a
candidate's (the higher of the slides' and the inverted data's rate, the latter with its tail
model beyond ``tail_from``) and checks the calibration: the number of data maxima with
``far <= x`` should be ``x`` times the data's live time. Optionally plots both, and with
``--out DIR`` writes both comparisons as ``levels.ecsv`` and ``calibration.ecsv`` there (each
naming its command, commit and date; the spreads and live times in their metadata).
"""
import argparse
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import numpy as np  # noqa: E402
import yaml  # noqa: E402
from sotodlib import core  # noqa: E402
from sotodlib.preprocess import Pipeline  # noqa: E402

import so_transients  # noqa: E402,F401  registers the steps and the loader
from astropy.table import Table  # noqa: E402

from so_transients.campaign.provenance import stamp  # noqa: E402
from so_transients.coherent.config import CoherentConfig  # noqa: E402
from so_transients.common import pointing  # noqa: E402
from so_transients.coherent.statistic import (
    false_alarm_rate, local_maxima, measured_scale, row_weights
)
from so_transients.coherent.vetoes import vetoed  # noqa: E402
from so_transients.detect.find import FindConfig, group_scans  # noqa: E402
from so_transients.common.scan_geometry import sample_rate  # noqa: E402
from so_transients.coherent.statistic import crossing_geometry  # noqa: E402
from so_transients.significance.far import SignificanceConfig, inverted_rate, scan_maps  # noqa: E402
from so_transients.sim.config import SimConfig  # noqa: E402
from so_transients.sim.simulate import simulate  # noqa: E402

CONFIG = os.path.join(os.path.dirname(__file__), "..", "configs", "preprocess_paper.yaml")


def filtered_group(minutes, tmp, seed, glitches=True):
    sim = simulate(SimConfig.from_dict({
        "output": tmp, "seed": seed, "observation": {"duration": 60.0 * minutes},
        "instrument": {"tubes": ["i1"], "wafers": ["w16"], "bands": ["f090"]},
        "glitches": {"enabled": glitches}}), progress=False)
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
        geometry = crossing_geometry(t, q, xi, eta, samples, sample_rate(t))
        snr = np.asarray(aman.transient_snr[dets, samples[0]:samples[-1] + 1])
        out.append(scan_maps(snr, geometry, beam, sigma, np.ones(len(dets), bool),
                             samples[0], cfg, CoherentConfig().vetoes, rng))
        snrs.append(snr)
    return out, beam, snrs, [sigma] * len(out)


def data_maxima(maps, snrs, sigmas, beam, scale):
    """Z of the local maxima of each data map in units of ``scale``, less those the coherent
    mode's glitch vetoes remove (maxima one detector makes, or detectors at one instant):
    the maxima that could be candidates."""
    out = []
    for m, snr, sigma in zip(maps, snrs, sigmas):
        window = m.geometry.crossing_samples(beam)
        r, s = local_maxima(m.z, 2.0 * scale, window)
        weights, _ = row_weights(m.geometry, m.rows, beam, sigma, np.ones(len(sigma), bool))
        keep = ~vetoed(snr, m.geometry, weights, beam, m.z[r, s] / scale, r, s,
                       CoherentConfig().vetoes)
        out.extend(m.z[r[keep], s[keep]] / scale)
    return np.asarray(out)


def calibration_plot(path, args, levels, observed, inverted, expected, combined, far_x,
                     n_below, live_data):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4))
    ax.errorbar(levels, observed, np.sqrt(observed), fmt="o", label="data: local maxima of Z")
    ax.plot(levels, np.where(inverted > 0, inverted, np.nan), "s", mfc="none",
            label="sign-inverted data (no source, same correlations)")
    ax.plot(levels, expected, "-", label="far_slides(Z) x live time")
    ax.plot(levels, combined, "--", label="far(Z) x live time (higher of slides, inverted)")
    ax.set_yscale("log")
    ax.set_xlabel("Z")
    ax.set_ylabel("number with statistic >= Z")
    ax.set_title(f"noise-only f090, {args.minutes:.0f} min of w16, {args.slides} slides")
    ax.legend(fontsize=8)
    expect = far_x * live_data
    bx.fill_between(far_x, np.maximum(expect - 2 * np.sqrt(expect), 0.1),
                    expect + 2 * np.sqrt(expect), alpha=0.3, label="x T +- 2 sqrt(x T)")
    bx.plot(far_x, expect, "-", label="x T (calibrated)")
    bx.plot(far_x, np.where(n_below > 0, n_below, np.nan), "o", label="data maxima, far <= x")
    bx.set_xscale("log")
    bx.set_yscale("log")
    bx.set_xlabel("x: false alarms per wafer-band-hour")
    bx.set_ylabel("number of data maxima with far <= x")
    bx.set_title(f"calibration of far, T = {live_data:.2f} h")
    bx.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"figure: {path}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--slides", type=int, default=20)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--slide-groups", type=int, default=SignificanceConfig.slide_groups,
                        metavar="G", help="detectors slid alike in G groups (0: each alone)")
    parser.add_argument("--no-glitches", action="store_true",
                        help="simulate without glitches (the failing-test tail's cause)")
    parser.add_argument("--plot", metavar="PNG")
    parser.add_argument("--out", type=Path, metavar="DIR",
                        help="write levels.ecsv and calibration.ecsv here")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        aman = filtered_group(args.minutes, tmp, args.seed, not args.no_glitches)
    print(f"simulated and filtered {aman.dets.count} x {aman.samps.count} in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    cfg = SignificanceConfig(n_slides=args.slides, background_floor=2.0, slide_floor=2.0,
                             slide_groups=args.slide_groups)
    t1 = time.perf_counter()
    maps, beam, snrs, sigmas = maps_of(aman, cfg)
    elapsed = time.perf_counter() - t1
    scale = float(np.median([s for m in maps for s in m.slide_scale]))
    data_scale = float(np.median([measured_scale(m.z, lags=m.geometry.lag_samples)
                                  for m in maps]))
    # the background maxima that pass the chi-squared test, as the data's maxima do
    background = np.concatenate([np.asarray(m.background)[np.asarray(m.background_ok, bool)]
                                 for m in maps]) / scale
    failing = np.concatenate([np.asarray(m.background)[~np.asarray(m.background_ok, bool)]
                              for m in maps]) / scale
    live_bg = sum(m.live_s for m in maps) / 3600.0
    live_data = live_bg / args.slides
    data_max = data_maxima(maps, snrs, sigmas, beam, data_scale)
    inverted_max = np.concatenate([m.inverted[m.inverted_ok] for m in maps]) / data_scale
    inverted_max = inverted_max[inverted_max >= 2.0]
    print(f"maps: {elapsed:.0f} s for {len(maps)} scans x (1 + {args.slides} slides); "
          f"Z spread: data {data_scale:.3f}, slides {scale:.3f} (ratio "
          f"{data_scale / scale:.3f}); live time: data {live_data:.2f} h, background "
          f"{live_bg:.1f} h")
    print("slides' maxima failing the chi-squared test at Z >= 5 / 6 / 7 / 8: "
          + " / ".join(str(int(np.sum(failing >= z))) for z in (5, 6, 7, 8))
          + f" (highest {failing.max() if len(failing) else float('nan'):.2f})")
    # the far of the data's own maxima, as transient_significance gives a candidate's
    far_slides = false_alarm_rate(data_max, background, live_bg)
    far = np.fmax(far_slides, inverted_rate(data_max, inverted_max, live_data, cfg.tail_from))
    levels = np.arange(3.0, 7.01, 0.5)
    expected = false_alarm_rate(levels, background, live_bg) * live_data
    combined = np.fmax(expected, inverted_rate(levels, inverted_max, live_data,
                                               cfg.tail_from) * live_data)
    observed = np.array([np.sum(data_max >= z) for z in levels])
    inverted = np.array([np.sum(inverted_max >= z) for z in levels])
    print(f"\n{'Z >=':>6}{'data maxima':>13}{'inverted data':>15}{'far_slides x T':>16}"
          f"{'far x T':>10}{'pull':>7}")
    for z, n, i, e, c in zip(levels, observed, inverted, expected, combined):
        print(f"{z:>6.1f}{n:>13d}{i:>15d}{e:>16.1f}{c:>10.1f}"
              f"{(n - c) / np.sqrt(max(c, 1)):>7.1f}")
    far_x = np.logspace(-1, np.log10(max(2000.0 / live_data, 1.0)), 13)
    n_below = np.array([np.sum(far <= x) for x in far_x])
    print(f"\n{'x (1/h)':>9}{'far <= x':>10}{'x T':>9}{'pull':>7}")
    for x, n in zip(far_x, n_below):
        e = x * live_data
        print(f"{x:>9.2f}{n:>10d}{e:>9.1f}{(n - e) / np.sqrt(max(e, 1)):>7.1f}")
    if args.plot:
        calibration_plot(args.plot, args, levels, observed, inverted, expected, combined,
                         far_x, n_below, live_data)
    if args.out:
        meta = dict(data_scale=data_scale, slide_scale=scale, live_data_hours=live_data,
                    live_background_hours=live_bg, comments=[
                        "python studies/far_calibration.py " + " ".join(sys.argv[1:] if argv
                                                                       is None else argv),
                        f"{stamp()}; the shipped standard steps of "
                        "configs/preprocess_paper.yaml and transient_filter"])
        write_tables(args.out, meta, dict(z=levels, data_maxima=observed,
                                          inverted_maxima=inverted,
                                          far_slides_x_live=expected, far_x_live=combined),
                     dict(far_per_hour=far_x, maxima_far_below=n_below,
                          expected=far_x * live_data))
    return 0


def write_tables(out, meta, levels, calibration):
    """``levels.ecsv`` (maxima above each Z against the backgrounds' prediction) and
    ``calibration.ecsv`` (maxima with far <= x against x times the live time) in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    for name, columns in (("levels", levels), ("calibration", calibration)):
        table = Table(columns, meta=meta)
        table.write(out / f"{name}.ecsv", overwrite=True)
    print(f"tables: {out}")


if __name__ == "__main__":
    sys.exit(main())
