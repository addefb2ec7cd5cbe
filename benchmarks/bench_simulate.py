"""Benchmark: simulate one wafer-band and report wall time and peak memory.

    python benchmarks/bench_simulate.py            # 20 minutes of w16 at f090
    python benchmarks/bench_simulate.py --hours 1  # the full-size hour (860 dets x 792,000 samples)

The target (foundation issue): peak resident memory below twice the size of the wafer-band's
signal array as float32 (2.7 GB for one hour). Prints a table and, with --json, a JSON line.
"""
import argparse
import json
import resource
import sys
import tempfile
import time

from so_transients.sim.config import SimConfig
from so_transients.sim.simulate import simulate


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=1 / 3)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    duration = args.hours * 3600
    config = SimConfig.from_dict({
        "seed": 1, "observation": {"duration": duration},
        "instrument": {"tubes": ["i1"], "wafers": ["w16"], "bands": ["f090"]},
        "flares": {"n": 10}, "glitches": {"enabled": True}})
    signal_bytes = 860 * int(round(duration * 220)) * 4
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        simulate(config, output=tmp, progress=sys.stderr.isatty())
        wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    result = {"duration_s": duration, "wall_s": round(wall, 1),
              "signal_gb": round(signal_bytes / 1e9, 3), "peak_rss_gb": round(peak / 1e9, 3),
              "peak_over_signal": round(peak / signal_bytes, 2), "target_peak_over_signal": 2.0}
    for key, value in result.items():
        print(f"{key:>24}: {value}")
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
