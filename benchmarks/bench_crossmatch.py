"""Benchmark: cross-matching detections with a source catalogue.

    python benchmarks/bench_crossmatch.py                       # 20k sources x 2000 events
    python benchmarks/bench_crossmatch.py --sources 200000 --events 20000

Random positions over the sky; times (best of ``--repeats``) the events' cross-match
(``so_transients.sources.crossmatch.crossmatch``, nearest catalogued source) and
``transient_cuts``' known-source mask (``near_known_source``, any source within 2'), both on
astropy's k-d tree, against the n x m matrix of separations they replaced, and checks that
both give the same answer. Target (issue "Into SO's environment"): 20k x 2000 under 0.1 s.
"""
import argparse
import time

import numpy as np

from so_transients.common.angles import ARCMIN, sky_separation
from so_transients.detect.cuts import near_known_source
from so_transients.sources.catalog import Catalogue
from so_transients.sources.crossmatch import CrossmatchConfig, crossmatch


def random_sky(rng, n):
    return rng.uniform(0, 2 * np.pi, n), np.arcsin(rng.uniform(-1, 1, n))


def best_of(repeats, func):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = func()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sources", type=int, default=20000)
    p.add_argument("--events", type=int, default=2000)
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)
    rng = np.random.default_rng(1)
    cat_ra, cat_dec = random_sky(rng, args.sources)
    ra, dec = random_sky(rng, args.events)
    ra[: args.events // 2] = cat_ra[: args.events // 2] + 0.5 * ARCMIN   # half near a source
    cat = Catalogue("bench", cat_ra, cat_dec, np.array([f"S{i}" for i in range(args.sources)]),
                    np.arange(args.sources).astype(str), np.full(args.sources, 100.0))
    cfg = CrossmatchConfig()
    flux = np.full(args.events, 500.0)
    t_match, out = best_of(args.repeats, lambda: crossmatch(ra, dec, flux, np.zeros(args.events),
                                                            cat, None, cfg))
    t_mask, mask = best_of(args.repeats,
                           lambda: near_known_source(ra, dec, cat_ra, cat_dec, 2 * ARCMIN))

    def matrix():
        sep = sky_separation(ra[None], dec[None], cat_ra[:, None], cat_dec[:, None])
        return np.argmin(sep, axis=0), (sep <= 2 * ARCMIN).any(axis=0)

    t_matrix, (nearest, old_mask) = best_of(1, matrix)
    matched = out["cat_source_id"] != ""                  # catalogue ids are text, '' for none
    assert np.array_equal(out["cat_source_id"][matched], nearest[matched].astype(str)), \
        "nearest differs"
    assert np.array_equal(mask, old_mask), "known-source mask differs"
    print(f"{args.sources} sources x {args.events} events: cross-match {t_match * 1e3:.1f} ms, "
          f"known-source mask {t_mask * 1e3:.1f} ms; the separation matrix took "
          f"{t_matrix * 1e3:.0f} ms ({t_matrix / max(t_match, t_mask):.0f}x slower); "
          f"{int(matched.sum())} matched (target: under 100 ms each)")


if __name__ == "__main__":
    main()
