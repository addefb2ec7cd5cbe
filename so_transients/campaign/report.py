"""The campaign's result tables, next to the reference paper's Table 2.

Written to the results folder: ``efficiency.ecsv``, ``thresholds.ecsv``, ``thresholds.md``,
``flux_residuals.ecsv``, ``pointing.ecsv``, ``false_positives.ecsv`` (and ``full_check.ecsv``
when the full-pipeline comparison ran), plus the figures of :mod:`.figures`. Units: mJy for
fluxes, s for times, arcsec for pointing offsets, detections per hour for rates.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.table import Table

from ..angles import ARCSEC
from ..bands import get_band
from .noise import group_info
from .stats import LEVELS, binomial_interval, thresholds

#: Clancy et al. 2025, Table 2: S_p (mJy) at 10 / 50 / 90 % efficiency, by band and t_r (s).
PAPER_TABLE2 = {
    "f090": {0.5: (400, 550, 800), 5: (250, 300, 400), 30: (200, 275, 325), 150: (175, 225, 300)},
    "f150": {0.5: (450, 650, 1150), 5: (250, 350, 500), 30: (225, 350, 450),
             150: (225, 300, 400)},
    "f220": {0.5: (650, 1000, 1650), 5: (425, 600, 900), 30: (400, 550, 800),
             150: (400, 550, 750)},
    "f280": {0.5: (1250, 1900, 4250), 5: (800, 1100, 1900), 30: (750, 1000, 1500),
             150: (700, 1000, 1600)},
}


def efficiency_table(flares: Table) -> Table:
    """Injected and detected flares per band, t_r and S_p, with 68 % Jeffreys intervals."""
    rows = []
    keys = sorted({(str(b), float(t), float(s)) for b, t, s in
                   zip(flares["band"], flares["t_rise"], flares["s_peak"])})
    for band, t_rise, s_peak in keys:
        sel = (flares["band"] == band) & (flares["t_rise"] == t_rise) & (flares["s_peak"] == s_peak)
        n, k = int(sel.sum()), int(flares["detected"][sel].sum())
        eff, lo, hi = binomial_interval(k, n)
        rows.append((band, t_rise, s_peak, n, k, float(eff), float(lo), float(hi),
                     int(flares["n_searched"][sel].sum()), int(flares["n_skipped"][sel].sum())))
    table = Table(rows=rows, names=("band", "t_rise", "s_peak", "injected", "detected",
                                    "efficiency", "eff_lo", "eff_hi", "crossings_searched",
                                    "crossings_skipped"),
                  dtype=("U8", float, float, int, int, float, float, float, int, int))
    table["t_rise"].unit, table["s_peak"].unit = u.s, u.mJy
    return table


def threshold_table(eff: Table, seed=0) -> Table:
    """S_p at 10 / 50 / 90 % efficiency per band and t_r, with the paper's values."""
    rows = []
    for band in sorted(set(eff["band"])):
        for t_rise in sorted(set(eff["t_rise"][eff["band"] == band])):
            sel = eff[(eff["band"] == band) & (eff["t_rise"] == t_rise)]
            found = thresholds(sel["s_peak"], sel["detected"], sel["injected"], seed=seed)
            paper = PAPER_TABLE2.get(band, {}).get(t_rise, (np.nan,) * 3)
            row = [band, t_rise]
            for level, ref in zip(LEVELS, paper):
                row += [found[level][0], found[level][1], float(ref)]
            rows.append(row)
    names = ["band", "t_rise"]
    for level in LEVELS:
        pct = int(round(100 * level))
        names += [f"s{pct}", f"s{pct}_err", f"paper_s{pct}"]
    table = Table(rows=rows, names=names, dtype=["U8"] + [float] * (len(names) - 1))
    for name in names[2:]:
        table[name].unit = u.mJy
    table["t_rise"].unit = u.s
    return table


def _fmt(value, err=np.nan):
    if not np.isfinite(value):
        return "—"
    return f"{value:.0f} ± {err:.0f}" if np.isfinite(err) else f"{value:.0f}"


def thresholds_markdown(table: Table, eff: Table) -> str:
    """One Markdown table per band: ours (± bootstrap error) | the paper's."""
    lines = ["# Flux density at 10 / 50 / 90 % detection efficiency", "",
             "S_p in mJy, interpolated on the (monotone) efficiency curve; ± is the bootstrap "
             "standard deviation. '—' marks a level not reached on the grid. Paper: Clancy et "
             "al. 2025, Table 2.", ""]
    for band in sorted(set(table["band"])):
        grid = sorted(set(eff["s_peak"][eff["band"] == band]))
        lines += [f"## {band} (grid {grid[0]:.0f}–{grid[-1]:.0f} mJy, "
                  f"{int(np.median(eff['injected'][eff['band'] == band]))} flares per cell)", "",
                  "| t_r (s) | 10 % | 50 % | 90 % | paper 10 % | paper 50 % | paper 90 % |",
                  "|---:|---:|---:|---:|---:|---:|---:|"]
        for row in table[table["band"] == band]:
            ours = [_fmt(row[f"s{p}"], row[f"s{p}_err"]) for p in (10, 50, 90)]
            paper = [_fmt(row[f"paper_s{p}"]) for p in (10, 50, 90)]
            lines.append(f"| {row['t_rise']:g} | " + " | ".join(ours + paper) + " |")
        lines.append("")
    return "\n".join(lines)


def flux_residual_table(detections: Table) -> Table:
    """Every matched detection with its fractional flux residuals."""
    if not len(detections):
        return Table(names=("bandpass", "t_rise", "s_peak", "flux", "flux_true", "residual",
                            "peak_residual", "nearest_peak"))
    keep = ["source_id", "obs_id", "wafer_slot", "bandpass", "t_rise", "s_peak", "t_peak",
            "flux", "flux_err", "flux_true", "snr_fit", "n_dets", "dt", "offset", "nearest_peak"]
    out = detections[[c for c in keep if c in detections.colnames]]
    flux_true = np.asarray(out["flux_true"], float)
    with np.errstate(divide="ignore", invalid="ignore"):
        out["residual"] = (np.asarray(out["flux"]) - flux_true) / flux_true
    out["peak_residual"] = (np.asarray(out["flux"]) - np.asarray(out["s_peak"])) \
        / np.asarray(out["s_peak"])
    return out


def pointing_table(detections: Table) -> Table:
    """Median and 68th percentile of fitted-position offsets per band, also / FWHM."""
    rows = []
    for band in sorted(set(detections["bandpass"])) if len(detections) else []:
        off = np.asarray(detections["offset"][detections["bandpass"] == band], float) / ARCSEC
        fwhm = get_band(band).fwhm / ARCSEC
        med, p68 = np.median(off), np.percentile(off, 68.27)
        rows.append((band, len(off), med, p68, fwhm, med / fwhm, p68 / fwhm))
    table = Table(rows=rows or None, names=("band", "n", "median", "p68", "fwhm",
                                            "median_over_fwhm", "p68_over_fwhm"),
                  dtype=("U8", int, float, float, float, float, float))
    for name in ("median", "p68", "fwhm"):
        table[name].unit = u.arcsec
    return table


def false_positive_table(folders: dict) -> Table:
    """False detections per band, noise-only and sign-inverted, with Poisson errors: per hour
    of the band's observations (all its wafers together), and per wafer-band-hour (one
    wafer's detectors of one band for one hour), the unit to compare between instruments
    (the paper's ~2 per hour over 24 MF wafer-bands is 0.08 per wafer-band-hour)."""
    return false_positive_rates({g: group_info(f) for g, f in folders.items()})


def false_positive_rates(infos: dict) -> Table:
    """:func:`false_positive_table` from each group's ``info`` (duration in s, counts)."""
    per_band = {}
    for group, info in infos.items():
        entry = per_band.setdefault(group.band, dict(obs=set(), wafers=set(), wafer_hours=0.0,
                                                     noise=0, inverted=0, seconds={}))
        entry["obs"].add(group.obs_id)
        entry["wafers"].add(group.wafer)
        entry["wafer_hours"] += info["duration"] / 3600
        entry["seconds"][group.obs_id] = info["duration"]
        entry["noise"] += info["n_false_noise"]
        entry["inverted"] += info["n_false_inverted"]
    rows = []
    for band, e in sorted(per_band.items()):
        hours, wbh = sum(e["seconds"].values()) / 3600, e["wafer_hours"]
        row = [band, len(e["obs"]), len(e["wafers"]), hours, wbh]
        for kind in ("noise", "inverted"):
            n, err = e[kind], np.sqrt(max(e[kind], 1))
            row += [n, n / hours, err / hours, n / wbh, err / wbh]
        rows.append(tuple(row))
    names = ["band", "n_obs", "n_wafers", "hours", "wafer_hours"]
    for kind in ("noise", "inverted"):
        names += [f"n_{kind}", f"rate_{kind}", f"rate_{kind}_err", f"rate_{kind}_per_wbh",
                  f"rate_{kind}_per_wbh_err"]
    table = Table(rows=rows or None, names=names,
                  dtype=["U8", int, int, float, float] + [int, float, float, float, float] * 2)
    for kind in ("noise", "inverted"):
        for name in (f"rate_{kind}", f"rate_{kind}_err"):
            table[name].unit = 1 / u.hour
        for name in (f"rate_{kind}_per_wbh", f"rate_{kind}_per_wbh_err"):
            table[name].unit = 1 / u.hour
            table[name].description = "per wafer-band-hour"
    table["hours"].unit = table["wafer_hours"].unit = u.hour
    table["wafer_hours"].description = "wafer-band-hours: wafers x hours of this band"
    return table


def noise_rms(folders: dict) -> dict:
    """Median per-sample white noise (mJy) of each band's detectors."""
    values = {}
    for group, folder in folders.items():
        info = group_info(folder)
        values.setdefault(group.band, []).append(info["noise_rms"])
    return {band: float(np.median(v)) for band, v in values.items()}


def write_results(cfg, folder, flares, detections, folders, check=None) -> Path:
    """Write every table and figure; returns ``folder``."""
    from .figures import write_figures

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    eff = efficiency_table(flares)
    limits = threshold_table(eff, cfg.seed)
    residuals = flux_residual_table(detections)
    pointing = pointing_table(detections)
    false = false_positive_table(folders)
    meta = {"config_digest": cfg.digest()}
    for name, table in (("efficiency", eff), ("thresholds", limits),
                        ("flux_residuals", residuals), ("pointing", pointing),
                        ("false_positives", false), ("full_check", check)):
        if table is not None:
            table.meta.update(meta)
            table.write(folder / f"{name}.ecsv", overwrite=True)
    (folder / "thresholds.md").write_text(thresholds_markdown(limits, eff))
    flares.write(folder / "flares.ecsv", overwrite=True)
    write_figures(folder, eff, residuals, noise_rms(folders))
    return folder
