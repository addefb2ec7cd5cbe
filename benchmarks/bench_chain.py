"""Benchmark: the transient detection chain against the FFT floor, on one simulated wafer-band.

    python benchmarks/bench_chain.py                  # 20 minutes of w16 at f090 (make bench)
    python benchmarks/bench_chain.py --hours 1        # the full-size hour (860 x 792,000)
    python benchmarks/bench_chain.py --workers 2      # the filter's threads
    python benchmarks/bench_chain.py --json out.json  # also write the figures as JSON
    python benchmarks/bench_chain.py --significance-slides 20   # with transient_significance
    python benchmarks/bench_chain.py --find-mode coherent       # transient_find's coherent mode
    python benchmarks/bench_chain.py --significance-slides 100 --slide-groups 0  # per detector

Simulates the TOD (white noise, atmosphere, CMB, flares and glitches), loads it through its
sotodlib Context, runs the standard steps of ``configs/preprocess_paper.yaml`` that come
before the transient search (turnaround flags, detrend, glitch flags, PSD, noise, PCA; not
timed), then times on that same array (median of ``--repeats`` runs):

1. the floor: ``scipy.fft`` rfft + irfft of every detector, padded to the filter's FFT length
   and in the filter's chunks of detectors;
2. the four transient steps run by sotodlib's preprocess ``Pipeline`` (per step, from the
   pipeline's own "Running <step>" log records, and in total);
3. the reference a user would otherwise write with sotodlib's tools: ``fft_ops.calc_psd`` for
   the noise, then ``filters.fourier_filter`` with the same high-pass x template / PSD, and the
   S/N normalization;
4. the chain's peak resident memory (the kernel's high-water mark, reset before the run) as a
   multiple of the signal array's size.

Targets (issue "Performance"), on one core: chain / floor <= 1.5; >= 2x faster than the
sotodlib-based filtering; peak memory <= 3x the signal; >= 150x real time.
"""
import argparse
import json
import logging
import os
import sys
import tempfile
import time

os.environ.setdefault("OMP_WAIT_POLICY", "passive")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import yaml  # noqa: E402
import scipy.fft  # noqa: E402
from sotodlib import core  # noqa: E402
from sotodlib.preprocess import Pipeline  # noqa: E402
from sotodlib.tod_ops import fft_ops, filters  # noqa: E402

import so_transients  # noqa: E402,F401  registers the steps and the loader
from so_transients.common.angles import ARCMIN  # noqa: E402
from so_transients.common.bands import fwhm_to_sigma  # noqa: E402
from so_transients.detect.matched_filter import FilterConfig, butterworth_highpass  # noqa: E402
from so_transients.common.scan_geometry import scan_speed  # noqa: E402
from so_transients.sim.config import SimConfig  # noqa: E402
from so_transients.sim.simulate import simulate  # noqa: E402

TARGETS = {"chain_over_floor": 1.5, "speedup_vs_sotodlib": 2.0, "peak_over_signal": 3.0,
           "realtime_factor": 150.0}


def standard_steps():
    """The standard sotodlib steps of the shipped site config, before the transient search."""
    path = os.path.join(os.path.dirname(__file__), "..", "configs", "preprocess_paper.yaml")
    with open(path) as f:
        steps = yaml.safe_load(f)["process_pipe"]
    return steps[:[s["name"] for s in steps].index("transient_filter")]


def pipeline_config(workers, significance_slides=0, find_mode="paper", slide_groups=None):
    """The transient steps (``transient_find`` in ``find_mode``); with
    ``significance_slides``, transient_significance with that many time slides (in
    ``slide_groups`` groups; None: its default) before transient_fit (its cost is then
    printed against the floor)."""
    calc = {"n_slides": significance_slides}
    if slide_groups is not None:
        calc["slide_groups"] = slide_groups
    extra = ([{"name": "transient_significance", "calc": calc, "save": True}]
             if significance_slides else [])
    return [
        {"name": "transient_filter", "process": {"workers": workers}, "calc": True, "save": True},
        {"name": "transient_find", "calc": {"mode": find_mode}, "save": True},
        {"name": "transient_cuts", "calc": {}, "save": True},
        *extra,
        {"name": "transient_fit", "calc": {}, "save": True},
    ]


class StepClock(logging.Handler):
    """Times each step from the Pipeline's "Running <step>" debug records."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.marks = []

    def emit(self, record):
        message = record.getMessage()
        if message.startswith("Running "):
            self.marks.append((message.split()[1], time.perf_counter()))

    def durations(self, end):
        times = [t for _, t in self.marks] + [end]
        return {name: times[i + 1] - times[i] for i, (name, _) in enumerate(self.marks)}


def reset_peak_rss():
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def rss(field):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field):
                return int(line.split()[1]) * 1024
    return 0


def clear_outputs(aman):
    for name in [n for n in aman._fields if n.startswith("transient_")]:
        aman.move(name, None)


def run_chain(aman, workers, significance_slides=0, find_mode="paper", slide_groups=None):
    clear_outputs(aman)
    logger = logging.getLogger("bench_chain.pipeline")
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    clock = StepClock()
    logger.handlers = [clock]
    pipe = Pipeline(pipeline_config(workers, significance_slides, find_mode, slide_groups),
                    logger=logger)
    reset_peak_rss()
    start = time.perf_counter()
    proc = pipe.run(aman)
    end = time.perf_counter()
    if isinstance(proc, tuple):
        proc = proc[0]
    steps = clock.durations(end)
    steps["total"] = end - start
    return steps, rss("VmHWM"), proc


def floor(signal, chunk):
    nfft = scipy.fft.next_fast_len(signal.shape[1], real=True)
    start = time.perf_counter()
    for s in range(0, len(signal), chunk):
        spec = scipy.fft.rfft(signal[s:s + chunk], n=nfft, axis=1)
        scipy.fft.irfft(spec, n=nfft, axis=1)
    return time.perf_counter() - start


@filters.fft_filter
def _weights(freqs, tod, psd_freqs=None, psd=None, sigma_t=None, fc=1.23):
    """high-pass x template / PSD, per detector (the sotodlib-based reference)."""
    tmpl = np.exp(-0.5 * (2 * np.pi * freqs * sigma_t) ** 2)
    inv = np.stack([1.0 / np.interp(freqs, psd_freqs, p) for p in psd])
    return (butterworth_highpass(freqs, fc) * tmpl)[None, :] * inv


def sotodlib_reference(aman, sigma_t):
    """The same filtering written with sotodlib's tools, and the S/N normalization."""
    start = time.perf_counter()
    freqs, pxx = fft_ops.calc_psd(aman, signal=aman.signal)
    n = fft_ops.find_superior_integer(aman.samps.count)
    rfft = fft_ops.RFFTObj.for_shape(aman.dets.count, n, "BOTH", threads=1)
    out = filters.fourier_filter(aman, _weights(psd_freqs=freqs, psd=pxx, sigma_t=sigma_t),
                                 detrend="linear", rfft=rfft)
    out /= np.std(out, axis=1)[:, None]
    return time.perf_counter() - start


def simulate_tod(hours, tmp):
    config = SimConfig.from_dict({
        "seed": 1, "output": tmp, "observation": {"duration": hours * 3600},
        "instrument": {"tubes": ["i1"], "wafers": ["w16"], "bands": ["f090"]},
        "flares": {"n": max(1, int(round(30 * hours)))}, "glitches": {"enabled": True}})
    result = simulate(config, progress=sys.stderr.isatty())
    return core.Context(str(result.context)).get_obs(result.obs_ids[0])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=1 / 3)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--skip-reference", action="store_true",
                        help="do not time the sotodlib-based filtering")
    parser.add_argument("--json", metavar="PATH")
    parser.add_argument("--significance-slides", type=int, default=0, metavar="N",
                        help="also run transient_significance with N time slides")
    parser.add_argument("--slide-groups", type=int, default=None, metavar="G",
                        help="transient_significance's slide_groups (default: its own)")
    parser.add_argument("--find-mode", choices=("paper", "coherent"), default="paper",
                        help="transient_find's mode")
    parser.add_argument("--context", metavar="YAML",
                        help="benchmark the first observation of this dataset instead")
    args = parser.parse_args(argv)

    t0 = time.perf_counter()
    if args.context:
        ctx = core.Context(args.context)
        aman = ctx.get_obs(ctx.obsdb.query()["obs_id"][0])
    else:
        with tempfile.TemporaryDirectory() as tmp:
            aman = simulate_tod(args.hours, tmp)
    Pipeline(standard_steps(), logger=logging.getLogger("bench_chain.standard")).run(aman)
    print(f"loaded and preprocessed {aman.dets.count} x {aman.samps.count} in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    signal = np.asarray(aman.signal)
    signal_bytes = signal.nbytes
    chunk = FilterConfig().chunk_dets
    slides = args.significance_slides
    run_chain(aman, args.workers, slides, args.find_mode, args.slide_groups)   # warm-up
    floors, chains, peaks = [], [], []
    for _ in range(args.repeats):
        floors.append(floor(signal, chunk))
        rss_before = rss("VmRSS")
        steps, peak, proc = run_chain(aman, args.workers, slides, args.find_mode,
                                      args.slide_groups)
        chains.append(steps)
        peaks.append((peak, rss_before))
    cands = aman.transient_candidates
    reference = None
    if not args.skip_reference:
        sigma_t = float(np.median(fwhm_to_sigma(2.2 * ARCMIN) / scan_speed(aman.timestamps, aman.boresight.az,
                                                                 aman.boresight.el)))
        reference = float(np.median([sotodlib_reference(aman, sigma_t)
                                     for _ in range(args.repeats)]))
    report(args, aman, signal_bytes, floors, chains, peaks, reference, cands)


def report(args, aman, signal_bytes, floors, chains, peaks, reference, cands):
    duration = float(aman.timestamps[-1] - aman.timestamps[0])
    names = [s["name"] for s in pipeline_config(1, args.significance_slides)]
    step_times = {name: float(np.median([c.get(name, np.nan) for c in chains]))
                  for name in (*names, "total")}
    total, floor_s = step_times["total"], float(np.median(floors))
    peak, before = max(p for p, _ in peaks), min(b for _, b in peaks)
    result = {
        "ndet": aman.dets.count, "nsamp": aman.samps.count, "duration_s": round(duration, 1),
        "workers": args.workers, "repeats": args.repeats, "find_mode": args.find_mode,
        "signal_gb": round(signal_bytes / 1e9, 3),
        "floor_s": round(floor_s, 2),
        **{f"{k}_s": round(v, 2) for k, v in step_times.items()},
        "sotodlib_filter_s": None if reference is None else round(reference, 2),
        "chain_over_floor": round(total / floor_s, 2),
        "filter_over_floor": round(step_times["transient_filter"] / floor_s, 2),
        "speedup_vs_sotodlib": None if reference is None else round(
            reference / step_times["transient_filter"], 2),
        "peak_rss_gb": round(peak / 1e9, 3),
        "peak_over_signal": round(peak / signal_bytes, 2),
        "added_over_signal": round((peak - before) / signal_bytes, 2),
        "realtime_factor": round(duration / total, 1),
        "candidates": len(cands.scan),
        "detections": int(np.sum(np.asarray(cands.detected, bool))),
    }
    print(f"\n{'stage':<22}{'seconds':>10}{'x floor':>10}")
    for name in ("floor", *names, "total"):
        value = floor_s if name == "floor" else step_times[name]
        print(f"{name:<22}{value:>10.2f}{value / floor_s:>10.2f}")
    if reference is not None:
        print(f"{'sotodlib filtering':<22}{reference:>10.2f}{reference / floor_s:>10.2f}")
    print()
    for key, target in TARGETS.items():
        value = result[key]
        if value is None:
            continue
        better = value <= target if key in ("chain_over_floor", "peak_over_signal") else value >= target
        sign = "<=" if key in ("chain_over_floor", "peak_over_signal") else ">="
        print(f"{key:<22}{value:>10}   target {sign} {target:<6} {'met' if better else 'NOT met'}")
    for key in ("added_over_signal", "candidates", "detections"):
        print(f"{key:<22}{result[key]:>10}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({**result, "targets": TARGETS}, f, indent=1)
    return result


if __name__ == "__main__":
    main()
