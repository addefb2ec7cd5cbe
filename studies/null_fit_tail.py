"""The beam fit's null distribution on drawn and ideal wafers: how far its tail exceeds a
Gaussian, and what the fits in the tail are made of.

    python studies/null_fit_tail.py                         # drawn 131, ideal 21, 30 minutes
    python studies/null_fit_tail.py --drawn 131 132 --ideal 21 22 --n-null 20000

``transient_fit``'s error scale is the clipped spread of ``A / sigma_A`` over random null
positions (:func:`so_transients.detect.error_scale.measure_error_scale`), and paper mode keeps fits
with ``A / sigma_A`` at 5 scales or more: its false-detection rate is the tail of that
distribution beyond 5, which 2000 null fits cannot see. Here each realization (a drawn wafer,
:func:`so_transients.campaign.drawn_wafer.drawn_config`, or the ideal wafer of
``studies/configs/ideal_wafer.yaml``; noise only, one f090 wafer-band) runs
``configs/preprocess_paper.yaml``'s steps up to ``transient_filter`` in process, and
``--n-null`` fits at random positions (as the error scale's) are divided by their clipped
spread. Written: ``null_fit_tail.ecsv`` (per realization: the scale, and in sweeps of each
scan direction and their range over single sweeps, the per-detector fit inflation's
spread, counts beyond 3-5 against a Gaussian's) and ``null_fit_tail_rows.ecsv``
(every fit beyond ``--row-level``: the share of its amplitude on its largest detector, that
detector's noise against the band's median and its peak S/N in the window, and the time to
the nearest cosmic ray the simulator put on that detector).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import numpy as np
import yaml
from astropy.table import Table
from scipy.stats import norm
from sotodlib import core
from sotodlib.preprocess import Pipeline

from so_transients.campaign.drawn_wafer import drawn_config
from so_transients.campaign.provenance import stamp
from so_transients.campaign.real_wafer import simulate_seed
from so_transients.campaign.search_steps import split_pipe
from so_transients.common import pointing
from so_transients.common.robust import clipped_std
from so_transients.common.scan_geometry import samples_in
from so_transients.detect.find import FindConfig, group_scans
from so_transients.detect.fit import (
    FitConfig, FitInputs, _beam_samples, fit_window, null_ratio, window_arrays
)
from so_transients.detect.matched_filter import expand_bins, filter_kernels, fit_error_inflation
from so_transients.site.pipeline import PAPER

ROOT = Path(__file__).resolve().parents[1]
IDEAL = ROOT / "studies" / "configs" / "ideal_wafer.yaml"
LEVELS = (3.0, 3.5, 4.0, 4.5, 5.0)


def filtered_group(sim):
    """The simulation's one f090 group through the paper config's steps up to
    ``transient_filter`` (sotodlib's Pipeline, in process)."""
    standard, _ = split_pipe(yaml.safe_load(Path(PAPER).read_text())["process_pipe"])
    ctx = core.Context(str(sim.context))
    aman = ctx.get_obs(sim.obs_ids[0], dets={"bandpass": "f090"})
    Pipeline(standard).run(aman)
    return aman


def detector_inflation(aman, live):
    """Each live detector's own fit-error inflation (from its PSD, knee and template width),
    against the band's one that the fit uses."""
    s = aman.transient_filter
    fs = 1.0 / np.median(np.diff(aman.timestamps))
    out = []
    for d in live:
        psd = expand_bins(np.asarray(s.psd_bins[d])[None], np.asarray(s.psd_edges))[0]
        _, response, acf = filter_kernels(int(s.nfft), fs, float(s.sigma_t[d]),
                                          float(s.fknee[d]), np.ravel(psd), int(s.order))
        out.append(fit_error_inflation(response, acf))
    return np.asarray(out)


def cosmic_ray_times(sim_root):
    """``{readout_id: ctimes}`` of the cosmic rays the simulator added."""
    path = Path(sim_root) / "truth" / "glitches.ecsv"
    times = {}
    if path.exists():
        for row in Table.read(path):
            for rid in str(row["readout_ids"]).split(","):
                times.setdefault(rid, []).append(float(row["ctime"]))
    return {k: np.asarray(v) for k, v in times.items()}


def null_positions(data, live, n_null, cfg, seed):
    """``(centres, ra, dec)``: ``n_null`` fit positions drawn uniformly over the observation
    and its live detectors (as :func:`so_transients.detect.error_scale.measure_error_scale` draws
    them where no candidate is to be avoided, from ``seed``)."""
    rng = np.random.default_rng(seed)
    t = data.timestamps
    n_win = samples_in(t, cfg.window)
    centres = rng.integers(n_win + 1, len(t) - n_win - 1, size=n_null)
    picks = rng.choice(live, size=n_null)
    ra, dec = pointing.radec_of_samples(data.bore_q, data.xi, data.eta, picks, centres)
    return centres, ra, dec


def null_window(data, live, centre, ra, dec, cfg):
    """``(near, window)``: the detectors of ``live`` a fit at (ra, dec) around sample
    ``centre`` uses, and its arrays as :func:`so_transients.detect.fit.null_ratio` takes
    them."""
    n_win = samples_in(data.timestamps, cfg.window)
    lo, hi = centre - n_win, centre + n_win + 1
    _, track, near = fit_window(data, ra, dec, lo, hi, live, cfg)
    return near, window_arrays(data, track, near, lo, hi)


def direction_scales(aman, data, centres, ratios) -> dict:
    """The clipped spread of the null fits in sweeps of increasing azimuth (``right``) and of
    decreasing azimuth (``left``), and its range over the single sweeps of each direction
    (``transient_find``'s scans; sweeps with fewer than 50 fits left out)."""
    good = np.isfinite(ratios)
    direction = data.direction[centres]
    scan, _ = group_scans(aman.timestamps, aman.boresight.az, aman.boresight.el, FindConfig())
    out = {}
    for name, d in (("right", 1), ("left", -1)):
        mine = good & (direction == d)
        out[f"scale_{name}"] = clipped_std(ratios[mine])
        per_scan = [clipped_std(ratios[mine & (scan[centres] == k)])
                    for k in np.unique(scan[centres][mine]) if k >= 0
                    and np.sum(mine & (scan[centres] == k)) >= 50]
        out[f"n_scans_{name}"] = len(per_scan)
        out[f"scan_scale_{name}_min"] = min(per_scan, default=np.nan)
        out[f"scan_scale_{name}_max"] = max(per_scan, default=np.nan)
    return out


def tail_row(data, aman, centre, z, near, window, rays, median_sigma):
    """What one fit in the tail is made of (see the module doc)."""
    beam, ok = _beam_samples(*window)
    amp, sigma = window[3], window[4]
    model = beam.model(np.array([1.0, 0.0, 0.0, 0.0]))
    per_sample = beam.w * model * beam.y / np.sum(beam.w * model * model)
    det_of = np.broadcast_to(np.arange(len(near))[:, None], amp.shape)[ok]
    shares = np.bincount(det_of, weights=per_sample, minlength=len(near))
    top = int(np.argmax(np.abs(shares)))
    det = near[top]
    rid = str(np.asarray(aman.det_info.readout_id)[det])
    t0 = float(data.timestamps[centre])
    on_det = rays.get(rid, np.zeros(0))
    return dict(z=float(z), t_obs=t0 - float(data.timestamps[0]), n_dets=len(near),
                top_share=float(shares[top] / np.sum(shares)), readout_id=rid,
                sigma_ratio=float(data.sigma_amp[det] / median_sigma),
                peak_snr=float(np.max(np.abs(amp[top])) / sigma[top]),
                dt_cosmic_ray=float(np.min(np.abs(on_det - t0))) if len(on_det) else np.nan)


def realization(kind, seed, folder, args):
    """One realization's summary row and tail rows."""
    config = drawn_config(seed) if kind == "drawn" else yaml.safe_load(IDEAL.read_text())
    sim = simulate_seed(folder, seed, args.minutes * 60, [], config)
    aman = filtered_group(sim)
    data = FitInputs.from_aman(aman, speed_tolerance=0.1)
    live = np.flatnonzero(~data.dead)
    cfg = FitConfig()
    inflation_band = float(data.kernel(live)[1])
    centres, ra, dec = null_positions(data, live, args.n_null, cfg, seed)
    ratios = np.array([null_ratio(null_window(data, live, c, r, d, cfg)[1], inflation_band)
                       for c, r, d in zip(centres, ra, dec)])     # windows not kept: GBs
    good = np.isfinite(ratios)
    scale = clipped_std(ratios[good])
    z = ratios / scale
    n = int(good.sum())
    inflation = detector_inflation(aman, live)
    row = dict(kind=kind, seed=seed, minutes=args.minutes, n_fits=n, error_scale=scale,
               **direction_scales(aman, data, centres, ratios), inflation_band=inflation_band,
               inflation_p5=float(np.percentile(inflation, 5)),
               inflation_p95=float(np.percentile(inflation, 95)))
    for level in LEVELS:
        row[f"n_beyond_{level:g}"] = int(np.sum(np.abs(z[good]) > level))
        row[f"gauss_beyond_{level:g}"] = float(2 * norm.sf(level) * n)
    rays = cosmic_ray_times(folder)
    median_sigma = float(np.median(data.sigma_amp[live]))
    tails = [dict(kind=kind, seed=seed,
                  **tail_row(data, aman, centres[k], z[k],
                             *null_window(data, live, centres[k], ra[k], dec[k], cfg),
                             rays, median_sigma))
             for k in np.flatnonzero(good & (np.abs(z) > args.row_level))]
    return row, tails


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--drawn", type=int, nargs="*", default=[131])
    p.add_argument("--ideal", type=int, nargs="*", default=[21])
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--n-null", type=int, default=20000)
    p.add_argument("--row-level", type=float, default=3.5)
    p.add_argument("--out", type=Path, default=Path("null_fit_tail.ecsv"))
    args = p.parse_args(argv)
    rows, tails = [], []
    with tempfile.TemporaryDirectory(prefix="null_fit_tail_") as tmp:
        for kind, seeds in (("drawn", args.drawn), ("ideal", args.ideal)):
            for seed in seeds:
                row, tail = realization(kind, seed, Path(tmp) / f"{kind}{seed}", args)
                rows.append(row)
                tails += tail
                print(row, flush=True)
    comments = [f"python studies/null_fit_tail.py {' '.join(sys.argv[1:])}".strip(),
                f"{stamp()}; configs/preprocess_paper.yaml's steps up to "
                "transient_filter, noise only, one f090 wafer-band"]
    summary = Table(rows=rows)
    summary.meta["comments"] = comments
    summary.write(args.out, overwrite=True)
    tail_table = Table(rows=tails) if tails else Table()
    tail_table.meta["comments"] = comments
    tail_table.write(args.out.with_name(args.out.stem + "_rows.ecsv"), overwrite=True)
    summary.pprint(max_width=-1)
    if tails:
        tail_table.sort("z")
        tail_table.pprint(max_lines=-1, max_width=-1)


if __name__ == "__main__":
    main()
