"""Benchmark: the coarse-to-fine search of time slides' maxima against the full maps.

    python studies/slide_search.py                        # 20 minutes of w16 at f090
    python studies/slide_search.py --context path/to/context.yaml --slides 10
    python studies/slide_search.py --floor 3.5            # more maxima to compare

Loads (or simulates, as ``bench_chain.py`` does: atmosphere, CMB, flares, glitches) one
observation, runs the shipped standard steps and ``transient_filter``, then for every scan
and ``--slides`` time slides finds the local maxima at least ``--floor`` x the map's spread
twice: by ``transient_significance``'s coarse-to-fine search
(:class:`so_transients.significance.slide_maxima.SlideSearch`) and on the full map
(:func:`so_transients.coherent.statistic.coherent_map`). Prints each maximum the search missed (its Z
and one detector's share of it: above 0.5 the background leaves it out anyway), the counts
missed and added, the time per slide of each, and the slides' maxima per hour of the
wafer-band from the floor.

It also prints what bounds a slide's cost: the screen (the coarse map every slide sums)
against its multiply-adds at the rate the same sum reaches with all its data in cache
(:func:`in_cache_rate`: what the sum could reach at best, however its reads were
arranged), and both for 100 slides (the default) against the observation's FFT floor
(``bench_chain.py``'s, measured in the same run).
"""
import argparse
import logging
import os
import sys
import tempfile
import time

os.environ.setdefault("OMP_WAIT_POLICY", "passive")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from numba import njit  # noqa: E402
from sotodlib import core  # noqa: E402
from sotodlib.preprocess import Pipeline  # noqa: E402

import so_transients  # noqa: E402,F401  registers the steps and the loader
from so_transients.common import pointing  # noqa: E402
from so_transients.coherent.statistic import (
    add_slice, coherent_map, finite_snr, local_maxima, row_offsets, time_slide_offsets
)
from so_transients.detect.find import FindConfig, group_scans  # noqa: E402
from so_transients.detect.matched_filter import FilterConfig  # noqa: E402
from so_transients.common.scan_geometry import sample_rate  # noqa: E402
from so_transients.coherent.statistic import crossing_geometry  # noqa: E402
from so_transients.significance.far import SignificanceConfig  # noqa: E402
from so_transients.significance.slide_maxima import SlideSearch  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks"))
from bench_chain import floor as fft_floor, simulate_tod, standard_steps  # noqa: E402


def filtered(args):
    if args.context:
        ctx = core.Context(args.context)
        aman = ctx.get_obs(ctx.obsdb.query()["obs_id"][0])
    else:
        with tempfile.TemporaryDirectory() as tmp:
            aman = simulate_tod(1 / 3, tmp)
    steps = standard_steps() + [{"name": "transient_filter", "calc": True, "save": True}]
    Pipeline(steps, logger=logging.getLogger("slide_search")).run(aman)
    return aman


def scans_of(aman):
    """Per scan: ``(snr, geometry)`` of the live detectors, and their sigma_amp and beam."""
    t = np.asarray(aman.timestamps)
    scan, _ = group_scans(t, aman.boresight.az, aman.boresight.el, FindConfig())
    f = aman.transient_filter
    dets = np.flatnonzero(~np.asarray(f.dead, bool))
    q = pointing.boresight_q(aman)
    xi, eta = np.asarray(aman.focal_plane.xi)[dets], np.asarray(aman.focal_plane.eta)[dets]
    out = []
    for s in np.unique(scan[scan >= 0]):
        samples = np.flatnonzero(scan == s)
        snr = finite_snr(np.asarray(aman.transient_snr[dets, samples[0]:samples[-1] + 1]))
        out.append((snr, crossing_geometry(t, q, xi, eta, samples, sample_rate(t))))
    return out, np.asarray(f.sigma_amp)[dets], float(np.median(np.asarray(f.beam_sigma)[dets]))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--context", metavar="YAML",
                        help="the first observation of this dataset instead of a simulation")
    parser.add_argument("--slides", type=int, default=5)
    parser.add_argument("--floor", type=float, default=SignificanceConfig().slide_floor)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    aman = filtered(args)
    floor_s = float(np.median([fft_floor(np.asarray(aman.signal), FilterConfig().chunk_dets)
                               for _ in range(3)]))
    scans, sigma, beam = scans_of(aman)
    del aman
    cfg, rng = SignificanceConfig(), np.random.default_rng(args.seed)
    live = np.ones(len(sigma), bool)
    found = missed = added = 0
    t_full = t_search = t_screen = hours = 0.0
    adds = 0
    for snr, g in scans:
        rows = row_offsets(g, beam, cfg.row_step)
        window = g.crossing_samples(beam)
        search = SlideSearch(snr, g, rows, beam, sigma, live, window)
        search.maxima(time_slide_offsets(len(sigma), snr.shape[1], 400, rng), args.floor)
        for _ in range(args.slides):
            offsets = time_slide_offsets(len(sigma), snr.shape[1],
                                         int(cfg.min_slide_s * g.sample_rate), rng)
            start = time.perf_counter()
            r, s, _, scale = search.maxima(offsets, args.floor)
            t_search += time.perf_counter() - start
            middle = time.perf_counter()
            coarse = search.coarse_map((g.lag_samples + offsets) % snr.shape[1])
            t_screen += time.perf_counter() - middle
            adds += np.count_nonzero(search.coarse_weights) * coarse.shape[1]
            middle = time.perf_counter()
            z, _ = coherent_map(snr, g, rows, beam, sigma, live, offsets, with_flux=False,
                                finite=True, dtype=np.float32)
            fr, fs = local_maxima(z, args.floor * scale, window)
            t_full += time.perf_counter() - middle
            mine, full = set(zip(r.tolist(), s.tolist())), set(zip(fr.tolist(), fs.tolist()))
            lost = sorted(full - mine)
            if lost:
                share = search.largest_share(*np.array(lost).T, offsets)
                print(f"missed: Z {[round(float(z[p] / scale), 2) for p in lost]}, one "
                      f"detector's share {np.round(share, 2).tolist()}")
            found, missed, added = found + len(full), missed + len(lost), \
                added + len(mine - full)
            hours += snr.shape[1] / g.sample_rate / 3600.0
    n = len(scans) * args.slides
    print(f"{len(scans)} scans x {args.slides} slides, {len(sigma)} live detectors, "
          f"floor {args.floor}")
    print(f"maxima of the full maps: {found} ({found / hours:.0f} per wafer-band-hour); "
          f"missed by the search: {missed}; added: {added}")
    print(f"per slide of a scan: full map {1e3 * t_full / n:.1f} ms, search "
          f"{1e3 * t_search / n:.1f} ms ({t_full / t_search:.1f}x faster)")
    rate = in_cache_rate(search.phases.shape[2])
    bound = adds / rate
    print(f"per slide of the observation: search {t_search / args.slides:.3f} s, its screen "
          f"{t_screen / args.slides:.3f} s ({adds / args.slides / 1e6:.0f} M multiply-adds, "
          f"{adds / t_screen / 1e9:.1f} G/s; in cache {rate / 1e9:.1f} G/s: "
          f"{bound / args.slides:.3f} s)")
    print(f"100 slides against the FFT floor ({floor_s:.2f} s): search "
          f"{100 * t_search / args.slides / floor_s:.2f}x, screen "
          f"{100 * t_screen / args.slides / floor_s:.2f}x, the screen's multiply-adds at "
          f"the in-cache rate {100 * bound / args.slides / floor_s:.2f}x")
    return 0


def in_cache_rate(ncol, nrow=23, repeats=200):
    """Multiply-adds per second of the screen's sum (int16 samples into float32 rows,
    :func:`so_transients.coherent.statistic.add_slice`) with all its data in cache: ``nrow`` rows of
    ``ncol``, added to ``repeats`` times."""
    acc = np.zeros((nrow, ncol), np.float32)
    src = np.ones((nrow, ncol + 8), np.int16)
    _add_rows(acc, src, 1)
    start = time.perf_counter()
    _add_rows(acc, src, repeats)
    return nrow * ncol * repeats / (time.perf_counter() - start)


@njit
def _add_rows(acc, src, repeats):
    for _ in range(repeats):
        for r in range(acc.shape[0]):
            add_slice(acc[r], src[r], np.float32(0.5), 0, acc.shape[1], 3)


if __name__ == "__main__":
    sys.exit(main())
