"""Benchmark: the production site config's whole process_pipe (sotodlib's steps and ours) per step.

    python benchmarks/bench_site.py                       # one hour of w16 at f090
    python benchmarks/bench_site.py --duration 600        # ten minutes (a quick check)
    python benchmarks/bench_site.py --band f150 --repeats 3 --json site.json
    python benchmarks/bench_site.py --mpi                 # several groups under 1, 2, 3 MPI ranks
    python benchmarks/bench_site.py --mpi --mpi-bands f090 f150 --mpi-duration 1200 --ranks 1 2

**One group** (default): simulates one wafer-band with ``configs/sim_realistic.yaml`` (the
simulator behind ``so-transients simulate``: dead, noisy and jumping detectors, time constants,
glitches, flares), loads it through its Context, then for each of ``--repeats`` runs (the
observation loaded afresh each time, loading not timed):

1. the FFT floor as ``benchmarks/bench_chain.py`` defines it: ``scipy.fft`` rfft + irfft of
   every detector of the group's signal, padded to a fast length, in the filter's chunks;
2. the config's whole ``process_pipe`` (default ``configs/preprocess_production.yaml``)
   through sotodlib's preprocess ``Pipeline``, which runs each step's process, calc, save,
   plot and select in turn; each step is timed (wall and CPU) from the pipeline's "Running
   <step>" log records, and its peak resident memory is the kernel's high-water mark, reset
   at the start of every step.

It prints, per step, wall-clock and CPU seconds, each per wafer-band-hour and against the
floor's own wall or CPU time in the same run (on a loaded machine the CPU ratios are the
steadier: a process waiting for a core loses wall time, not CPU time), and the step's peak
RSS; then the totals of the standard steps (sotodlib's and this package's chunked equivalents
of them: the data's preparation), of ours (the search) and of the whole pipeline with their
real-time factors per core, the peak RSS against the signal's size, the load average, the
issue's targets, and what the measured cost means for the LAT (36 MF/UHF wafer-bands, 42 with
the LF tube, 24 h of observation a day; cost and memory scaled by each flavour's sample
rate). Figures are medians over the repeats.

**Several groups** (``--mpi``): simulates ``--mpi-bands`` of one wafer for ``--mpi-duration``
and runs sotodlib's site pipeline (``python -m so_transients.site.run``, i.e.
``preprocess_tod``) on the config pointed at that dataset under ``mpiexec -n N`` for each N of
``--ranks``, each into a fresh archive. sotodlib's ``get_exec_env`` makes rank 0 a dispatcher
and the other ranks workers. One rank has no MPI worker, so sotodlib falls back to a process
pool (``--nproc 1``: one worker process); under ``mpiexec -n 1`` that pool's spawned worker
inherits the launcher's PMI connection and dies at MPI start-up, so N = 1 runs without
``mpiexec`` (a singleton MPI process, as ``so-transients run`` does). It prints the wall
time, the working processes, the speed-up against the first N, the CPU time of all ranks and
of the busiest (the wall time with a free core per rank), the peak RSS of each rank (and of
rank 0's pool worker) and the candidates archived.

Nothing is asserted: timings depend on the host and its load (compare ratios measured in one
run).
"""
import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "passive")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import yaml  # noqa: E402
from sotodlib import core  # noqa: E402
from sotodlib.preprocess import Pipeline  # noqa: E402

from bench_chain import StepClock, floor, reset_peak_rss, rss  # noqa: E402
from so_transients.common.bands import FLAVOR_SAMPLE_RATE  # noqa: E402
from so_transients.detect.matched_filter import FilterConfig  # noqa: E402
from so_transients.sim.config import load_config  # noqa: E402
from so_transients.sim.simulate import simulate  # noqa: E402
from so_transients.site.pipeline import (PRODUCTION, failed_groups, standalone_env,  # noqa: E402
                                         write_site_config)

REPO = Path(__file__).resolve().parents[1]
SIM_CONFIG = REPO / "configs" / "sim_realistic.yaml"
#: wafer-bands of the LAT by tube flavour: four MF and two UHF tubes of 3 wafers x 2 bands, and
#: the LF tube's 6 (not simulated: costed at the measured band's sample rate)
LAT_WAFER_BANDS = {"LAT_MF": 24, "LAT_UHF": 12, "LAT_LF": 6}
#: issue targets: ratios to the floor (at most), real-time factors per core (at least)
TARGETS = {"transient_filter_over_floor": 1.5, "ours_over_floor": 2.5, "ours_realtime": 150.0,
           "pipeline_realtime": 60.0, "peak_over_signal": 3.0}
#: this package's chunked equivalents of sotodlib's standard steps: counted with the standard
#: steps (the split is "the search" against "the data's preparation")
STANDARD_EQUIVALENTS = {"transient_fourier_filter", "transient_glitches", "transient_pca_filter"}
#: folder where each rank writes its resource use (rank_<n>.json)
RANK_DIR = "BENCH_SITE_RANK_DIR"


class StepMeter(StepClock):
    """:class:`StepClock` that also notes the CPU time and the resident-memory high-water mark
    of each step (the mark is reset as each step starts)."""

    def __init__(self):
        super().__init__()
        self.cpu = []
        self.peaks = []

    def emit(self, record):
        if record.getMessage().startswith("Running "):
            self.peaks.append(rss("VmHWM"))
            reset_peak_rss()
            self.cpu.append(time.process_time())
        super().emit(record)

    def steps(self, end, cpu_end):
        """[(name, wall s, cpu s, peak RSS bytes)] in the order the steps ran."""
        walls = list(self.durations_list(end))
        cpus = np.diff([*self.cpu, cpu_end])
        peaks = [*self.peaks[1:], rss("VmHWM")]
        return [(name, w, float(c), p) for (name, w), c, p in zip(walls, cpus, peaks)]

    def durations_list(self, end):
        times = [t for _, t in self.marks] + [end]
        return [(name, times[i + 1] - times[i]) for i, (name, _) in enumerate(self.marks)]


def step_labels(process_pipe):
    """A label per step: its name, with the filter function for sotodlib's fourier_filter."""
    labels = []
    for step in process_pipe:
        fn = (step.get("process") or {}).get("filt_function")
        labels.append(f"{step['name']}:{fn}" if fn else step["name"])
    return labels


def simulate_dataset(out, duration, bands, wafer, tube, sim_config=SIM_CONFIG):
    """Simulate ``bands`` of one wafer for ``duration`` s into ``out`` (the simulator of
    ``so-transients simulate``); returns its context path and first obs_id."""
    config = load_config(str(sim_config), {
        "output": str(out), "observation": {"duration": duration},
        "instrument": {"tubes": [tube], "wafers": [wafer], "bands": list(bands)}})
    result = simulate(config, progress=sys.stderr.isatty())
    return result.context, result.obs_ids[0]


def run_pipeline(aman, process_pipe, plot_dir):
    """The whole ``process_pipe`` on ``aman`` through sotodlib's Pipeline, step by step."""
    import logging

    logger = logging.getLogger("bench_site.pipeline")
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    meter = StepMeter()
    logger.handlers = [meter]
    pipe = Pipeline(process_pipe, plot_dir=plot_dir, logger=logger)
    rss_before = rss("VmRSS")
    reset_peak_rss()
    start, cpu_start = time.perf_counter(), time.process_time()
    pipe.run(aman)
    end, cpu_end = time.perf_counter(), time.process_time()
    return {"steps": meter.steps(end, cpu_end), "wall": end - start, "cpu": cpu_end - cpu_start,
            "rss_before": rss_before}


def one_group(args):
    with open(args.config) as f:
        process_pipe = yaml.safe_load(f)["process_pipe"]
    labels = step_labels(process_pipe)
    load = [os.getloadavg()]
    with tempfile.TemporaryDirectory(prefix="bench_site_") as tmp:
        t0 = time.perf_counter()
        context, obs_id = simulate_dataset(Path(tmp) / "data", args.duration, [args.band],
                                           args.wafer, args.tube)
        print(f"simulated {args.duration:.0f} s of {args.wafer} {args.band} in "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
        ctx = core.Context(str(context))
        runs = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            aman = ctx.get_obs(obs_id)
            loaded = time.perf_counter() - t0
            signal_bytes = aman.signal.nbytes
            shape = aman.signal.shape
            duration = float(aman.timestamps[-1] - aman.timestamps[0])
            cpu0 = time.process_time()
            floor_s = floor(np.asarray(aman.signal), FilterConfig().chunk_dets)
            floor_cpu = time.process_time() - cpu0
            run = run_pipeline(aman, process_pipe, str(Path(tmp) / "plots"))
            run.update(floor=floor_s, floor_cpu=floor_cpu, load=loaded,
                       ndets_out=aman.dets.count)
            runs.append(run)
            del aman
        load.append(os.getloadavg())
    return report_group(args, labels, runs, shape, duration, signal_bytes, load)


def report_group(args, labels, runs, shape, duration, signal_bytes, load):
    med = lambda values: float(np.median(values))  # noqa: E731
    per_hour = 3600.0 / duration
    floor_s = med([r["floor"] for r in runs])
    floor_cpu = med([r["floor_cpu"] for r in runs])
    steps = []
    for i, label in enumerate(labels):
        ran = [r["steps"][i] for r in runs if i < len(r["steps"])]
        if not ran:
            continue
        wall, cpu = med([s[1] for s in ran]), med([s[2] for s in ran])
        steps.append({"step": label, "ours": label.startswith("transient_")
                      and label.split(":")[0] not in STANDARD_EQUIVALENTS,
                      "seconds": round(wall, 3), "cpu_seconds": round(cpu, 3),
                      "s_per_wbh": round(wall * per_hour, 2),
                      "cpu_s_per_wbh": round(cpu * per_hour, 2),
                      "over_floor": round(wall / floor_s, 3),
                      "cpu_over_floor": round(cpu / floor_cpu, 3),
                      "peak_rss_gb": round(max(s[3] for s in ran) / 1e9, 3)})
    ours = sum(s["seconds"] for s in steps if s["ours"])
    standard = sum(s["seconds"] for s in steps if not s["ours"])
    total = med([r["wall"] for r in runs])
    cpu = {"ours": sum(s["cpu_seconds"] for s in steps if s["ours"]),
           "standard": sum(s["cpu_seconds"] for s in steps if not s["ours"]),
           "pipeline": med([r["cpu"] for r in runs])}
    peak = max(max(s[3] for s in r["steps"]) for r in runs)
    result = {
        "config": os.path.relpath(args.config, REPO), "band": args.band, "wafer": args.wafer,
        "ndet": shape[0], "nsamp": shape[1], "ndet_after_cuts": runs[-1]["ndets_out"],
        "duration_s": round(duration, 1), "sample_rate": round(shape[1] / duration, 1),
        "repeats": args.repeats,
        "signal_gb": round(signal_bytes / 1e9, 3), "load_s": round(med([r["load"] for r in runs]), 2),
        "floor_s": round(floor_s, 3), "floor_s_per_wbh": round(floor_s * per_hour, 2),
        "floor_cpu_s": round(floor_cpu, 3),
        "steps": steps,
        "standard_s": round(standard, 2), "ours_s": round(ours, 2), "pipeline_s": round(total, 2),
        "pipeline_cpu_over_wall": round(med([r["cpu"] / r["wall"] for r in runs]), 3),
        "standard_over_floor": round(standard / floor_s, 2),
        "ours_over_floor": round(ours / floor_s, 2),
        "pipeline_over_floor": round(total / floor_s, 2),
        "transient_filter_over_floor": next(
            (s["over_floor"] for s in steps if s["step"] == "transient_filter"), None),
        "transient_filter_cpu_over_floor": next(
            (s["cpu_over_floor"] for s in steps if s["step"] == "transient_filter"), None),
        "standard_realtime": round(duration / standard, 1),
        "ours_realtime": round(duration / ours, 1),
        "pipeline_realtime": round(duration / total, 1),
        **{f"{k}_cpu_s": round(v, 2) for k, v in cpu.items()},
        **{f"{k}_cpu_over_floor": round(v / floor_cpu, 2) for k, v in cpu.items()},
        **{f"{k}_cpu_realtime": round(duration / v, 1) for k, v in cpu.items()},
        "peak_rss_gb": round(peak / 1e9, 3),
        "peak_over_signal": round(peak / signal_bytes, 2),
        "added_over_signal": round((peak - min(r["rss_before"] for r in runs)) / signal_bytes, 2),
        "rss_before_gb": round(min(r["rss_before"] for r in runs) / 1e9, 3),
        "loadavg_start": [round(v, 2) for v in load[0]],
        "loadavg_end": [round(v, 2) for v in load[-1]], "nproc": os.cpu_count(),
    }
    result["lat"] = lat_scale(result)
    print(f"\n{result['ndet']} x {result['nsamp']} ({duration:.0f} s of {args.wafer} "
          f"{args.band}; {result['ndet_after_cuts']} detectors after the cuts), signal "
          f"{result['signal_gb']} GB, median of {args.repeats}; config {result['config']}")
    head = ("", "wall s", "s/wbh", "x floor", "cpu s", "s/wbh", "x floor", "peak GB")
    print(f"\n{'':<34}{'-- wall clock --':^27}{'-- CPU time --':^27}")
    print(f"{'step':<34}" + "".join(f"{h:>9}" for h in head[1:]))

    def row(name, wall, cpu, peak=None):
        cells = (wall, wall * per_hour, wall / floor_s, cpu, cpu * per_hour, cpu / floor_cpu)
        print(f"{name:<34}" + "".join(f"{v:>9.2f}" for v in cells)
              + (f"{peak:>9.2f}" if peak is not None else f"{'':>9}"))

    row("FFT floor (rfft + irfft)", floor_s, floor_cpu)
    for s in steps:
        row(s["step"], s["seconds"], s["cpu_seconds"], s["peak_rss_gb"])
    print()
    for name, key in (("standard steps", "standard"), ("our steps", "ours"),
                      ("whole pipeline", "pipeline")):
        row(name, result[f"{key}_s"], result[f"{key}_cpu_s"])
    print("\nreal time per core (wall, CPU): " + "; ".join(
        f"{name} {result[f'{key}_realtime']}x, {result[f'{key}_cpu_realtime']}x"
        for name, key in (("standard steps", "standard"), ("ours", "ours"),
                          ("whole pipeline", "pipeline"))))
    print(f"loading the observation (before the pipeline, not in it): {result['load_s']} s")
    print(f"\npeak RSS {result['peak_rss_gb']} GB = {result['peak_over_signal']}x the signal "
          f"({result['added_over_signal']}x added by the pipeline); pipeline CPU/wall "
          f"{result['pipeline_cpu_over_wall']}; load average {result['loadavg_start']} -> "
          f"{result['loadavg_end']} on {result['nproc']} cores")
    print(f"\n{'target':<30}{'wall':>9}{'CPU':>9}")
    for key, target in TARGETS.items():
        at_most = key.endswith(("over_floor", "over_signal"))
        cpu_key = key.replace("_over_floor", "_cpu_over_floor").replace("_realtime",
                                                                         "_cpu_realtime")
        values = [result[key], result.get(cpu_key, result[key])]
        met = ["met" if (v <= target if at_most else v >= target) else "NOT met"
               for v in values]
        print(f"{key:<30}{values[0]:>9}{values[1]:>9}   {'<=' if at_most else '>='} "
              f"{target:<6} {met[0]} (wall), {met[1]} (CPU)")
    print("\nLAT scale (24 h of observation a day; one group per core at a time):")
    for name, lat in result["lat"].items():
        print(f"  {name:<10} {lat['wafer_bands']} wafer-bands "
              f"({lat['measured_band_equivalents']} of the measured band's samples): "
              f"{lat['cores']:.1f} cores busy all day by wall clock ({lat['cores_cpu']:.1f} by "
              f"CPU time; {lat['cores_ours']:.1f} for our steps alone); {lat['memory_gb']:.0f} GB "
              f"for that many one-hour groups at once (up to {lat['largest_group_gb']} GB each, "
              f"peak RSS scaled by samples)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({**result, "targets": TARGETS}, f, indent=1)
    return result


def lat_scale(result):
    """Cores (all day) and memory (one one-hour group per core) to keep up with the LAT, the
    measured cost scaled to each flavour's sample rate (the cost and the signal grow with the
    samples; every wafer-band has the same detectors); a group's memory is the process without
    data plus the rest of the measured peak scaled to an hour at that rate."""
    rate = result["sample_rate"]
    scale = {f: FLAVOR_SAMPLE_RATE.get(f, rate) / rate for f in LAT_WAFER_BANDS}
    out = {}
    for name, flavours in (("MF+UHF", ("LAT_MF", "LAT_UHF")),
                           ("MF+UHF+LF", ("LAT_MF", "LAT_UHF", "LAT_LF"))):
        equivalent = sum(LAT_WAFER_BANDS[f] * scale[f] for f in flavours)
        cores = equivalent / result["pipeline_realtime"]
        base = result["rss_before_gb"] - result["signal_gb"]     # the process without data
        group_gb = base + (result["peak_rss_gb"] - base) * 3600 / result["duration_s"] * max(
            scale[f] for f in flavours)
        out[name] = {"wafer_bands": sum(LAT_WAFER_BANDS[f] for f in flavours),
                     "measured_band_equivalents": round(equivalent, 1),
                     "cores": round(cores, 2),
                     "cores_cpu": round(equivalent / result["pipeline_cpu_realtime"], 2),
                     "cores_ours": round(equivalent / result["ours_realtime"], 2),
                     "largest_group_gb": round(group_gb, 1),
                     "memory_gb": round(np.ceil(cores) * group_gb, 1)}
    return out


def rank_run(argv):
    """Run sotodlib's site pipeline as one MPI rank, then write this rank's resource use to
    ``$BENCH_SITE_RANK_DIR/rank_<n>.json``."""
    from so_transients.site import run

    start = time.perf_counter()
    run.main(argv)
    me, children = (resource.getrusage(who) for who in
                    (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    rank = int(os.environ.get("PMI_RANK", os.environ.get("OMPI_COMM_WORLD_RANK", 0)))
    usage = {"rank": rank, "wall": time.perf_counter() - start, "cpu": me.ru_utime + me.ru_stime,
             "maxrss_gb": rss("VmHWM") / 1e9,    # ru_maxrss would keep the launcher's peak
             "children_cpu": children.ru_utime + children.ru_stime,
             "children_maxrss_gb": children.ru_maxrss * 1024 / 1e9}
    with open(Path(os.environ[RANK_DIR]) / f"rank_{rank}.json", "w") as f:
        json.dump(usage, f)


def several_groups(args):
    mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent))
    if mpiexec is None:
        sys.exit("no mpiexec beside the interpreter (pip install '.[test]' brings mpich)")
    env = standalone_env()
    env.update(OMP_NUM_THREADS="1", OMP_WAIT_POLICY="passive")
    load = [os.getloadavg()]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_site_mpi_") as tmp:
        t0 = time.perf_counter()
        simulate_dataset(Path(tmp) / "data", args.mpi_duration, args.mpi_bands, args.wafer,
                         args.tube)
        print(f"simulated {args.mpi_duration:.0f} s of {args.wafer} in "
              f"{' '.join(args.mpi_bands)} in {time.perf_counter() - t0:.0f} s", flush=True)
        for n in args.ranks:
            config = write_site_config(Path(tmp) / "data", path=Path(tmp) / f"n{n}.yaml",
                                       template=args.config, results=Path(tmp) / f"n{n}")
            workers = max(1, n - 1)
            cmd = ([mpiexec, "-n", str(n)] if n > 1 else []) + [
                sys.executable, str(Path(__file__).resolve()), "--rank-run", str(config),
                "--nproc", str(workers), "--verbosity", "1", "--pb-path", tmp]
            env[RANK_DIR] = str(Path(tmp) / f"n{n}")
            Path(env[RANK_DIR]).mkdir(parents=True, exist_ok=True)
            start = time.perf_counter()
            done = subprocess.run(cmd, env=env, cwd=tmp, capture_output=True, text=True)
            wall = time.perf_counter() - start
            if done.returncode != 0:
                sys.exit(f"{' '.join(cmd[:3])} failed:\n{done.stderr[-3000:]}")
            ranks = sorted((json.loads(p.read_text()) for p in
                            Path(env[RANK_DIR]).glob("rank_*.json")), key=lambda r: r["rank"])
            from so_transients.site.results import archive_table

            rows.append({"ranks": n, "workers": workers, "wall_s": round(wall, 1),
                         "failed": failed_groups(config),
                         "candidates": len(archive_table(config, detected_only=False)),
                         "per_rank": ranks})
            print(f"{'mpiexec -n ' + str(n) if n > 1 else 'no mpiexec'}: {wall:.1f} s",
                  flush=True)
            load.append(os.getloadavg())
    group_hours = len(args.mpi_bands) * args.mpi_duration / 3600
    base = rows[0]["wall_s"]
    print(f"\n{len(args.mpi_bands)} groups ({args.wafer} {' '.join(args.mpi_bands)}), "
          f"{args.mpi_duration:.0f} s each: {group_hours:.2f} wafer-band-hours; config "
          f"{os.path.relpath(args.config, REPO)}")
    print(f"{'ranks':>6}{'workers':>9}{'wall s':>9}{'speed-up':>10}{'s/wbh':>9}"
          f"{'CPU s':>8}{'max/wkr':>9}{'cands':>7}   peak RSS per rank (GB; +pool worker)")
    for row in rows:
        work = [r["cpu"] + r["children_cpu"] for r in row["per_rank"]]
        row["cpu_s"] = round(sum(work), 1)
        row["busiest_worker_cpu_s"] = round(max(work), 1)
        peaks = ", ".join(f"r{r['rank']} {r['maxrss_gb']:.2f}"
                          + (f" +{r['children_maxrss_gb']:.2f}" if r["children_maxrss_gb"] > 0.05
                             else "") for r in row["per_rank"])
        row["speedup"] = round(base / row["wall_s"], 2)
        print(f"{row['ranks']:>6}{row['workers']:>9}{row['wall_s']:>9.1f}{row['speedup']:>10.2f}"
              f"{row['wall_s'] / group_hours:>9.0f}{row['cpu_s']:>8.1f}"
              f"{row['busiest_worker_cpu_s']:>9.1f}{row['candidates']:>7}   {peaks}"
              + (f"   FAILED: {len(re.findall(r'^[0-9.]+, ', row['failed'], re.M))} "
                 "group(s), see the JSON" if row["failed"] else ""))
    print("CPU s: all ranks and pool workers; max/wkr: the busiest rank's (the wall time each "
          "run would take with a core per rank)")
    print(f"load average {[round(v, 2) for v in load[0]]} -> {[round(v, 2) for v in load[-1]]} "
          f"on {os.cpu_count()} cores")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"groups": len(args.mpi_bands), "duration_s": args.mpi_duration,
                       "runs": rows, "loadavg": load}, f, indent=1)
    return rows


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--rank-run"]:
        return rank_run(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(PRODUCTION), help="site preprocess config")
    parser.add_argument("--duration", type=float, default=3600.0, help="seconds simulated")
    parser.add_argument("--band", default="f090")
    parser.add_argument("--wafer", default="w16")
    parser.add_argument("--tube", default="i1")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--json", metavar="OUT", help="also write the figures as JSON")
    parser.add_argument("--mpi", action="store_true",
                        help="run several groups through the site pipeline under MPI instead")
    parser.add_argument("--mpi-bands", nargs="+", default=["f090", "f150"])
    parser.add_argument("--mpi-duration", type=float, default=1200.0)
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 3],
                        help="MPI ranks of each run (rank 0 dispatches)")
    args = parser.parse_args(argv)
    return several_groups(args) if args.mpi else one_group(args)


if __name__ == "__main__":
    main()
