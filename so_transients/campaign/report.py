"""The campaign's result tables, next to the reference paper's Table 2.

Written to the results folder: ``efficiency.ecsv``, ``thresholds.ecsv``, ``thresholds.md``,
``flux_residuals.ecsv`` and its per-t_r ``flux_summary.ecsv``, ``pointing.ecsv``,
``false_positives.ecsv``, ``fitted_noise.ecsv`` (every candidate fitted on the noise-only data),
``equal_rate.ecsv`` with ``efficiency_equal_rate.ecsv`` and ``thresholds_equal_rate.ecsv``
(:mod:`.equal_rate`), ``full_check.ecsv`` when the full-pipeline comparison ran; in coherent
mode ``far_background.ecsv`` and ``far_live.ecsv`` (the noise-only false-alarm background),
``far_budget.ecsv`` with ``efficiency_far.ecsv``, ``thresholds_far.ecsv`` and ``noise_far.ecsv``
(:mod:`.far_budget`); ``summary.md``
(:mod:`.markdown`: everything above as the README shows it), plus the figures of
:mod:`.figures`. Units: mJy for
fluxes, s for times, arcsec for pointing offsets, detections per hour for rates.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.table import Table, vstack

from so_transients.common.angles import ARCSEC
from so_transients.common.bands import get_band
from so_transients.campaign.noise import group_info
from so_transients.campaign.provenance import repository_path, stamp
from so_transients.campaign.far_budget import background_tables
from so_transients.campaign.stats import LEVELS, binomial_interval, thresholds

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


#: Clancy et al. 2025, section 5.2: median offset of the fitted positions (arcsec) per band.
PAPER_POINTING_ARCSEC = {"f090": 14.6, "f150": 7.0, "f220": 9.4, "f280": 9.1}


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
            "flux", "flux_err", "flux_true", "snr_fit", "map_z", "coherent_snr", "n_crossings",
            "n_dets", "dt", "offset", "nearest_peak"]
    out = detections[[c for c in keep if c in detections.colnames]]
    flux_true = np.asarray(out["flux_true"], float)
    with np.errstate(divide="ignore", invalid="ignore"):
        out["residual"] = (np.asarray(out["flux"]) - flux_true) / flux_true
    out["peak_residual"] = (np.asarray(out["flux"]) - np.asarray(out["s_peak"])) \
        / np.asarray(out["s_peak"])
    return out


def flux_summary_table(residuals: Table) -> Table:
    """Per band and t_r: median and scatter (half the 16-84 % range) of the fractional flux
    residuals of every matched detection (against the injected flux at its time), and the
    median against S_p of the detection nearest each flare's peak."""
    rows = []
    for band in sorted(set(residuals["bandpass"])) if len(residuals) else []:
        mine = residuals[residuals["bandpass"] == band]
        for t_rise in sorted(set(np.asarray(mine["t_rise"], float))):
            cell = mine[np.asarray(mine["t_rise"], float) == t_rise]
            r = np.asarray(cell["residual"], float)
            r = r[np.isfinite(r)]
            lo, med, hi = np.percentile(r, [15.87, 50, 84.13]) if len(r) else (np.nan,) * 3
            near = np.asarray(cell["peak_residual"], float)[np.asarray(cell["nearest_peak"], bool)]
            rows.append((band, t_rise, len(r), med, (hi - lo) / 2,
                         float(np.median(near)) if len(near) else np.nan))
    table = Table(rows=rows or None, names=("band", "t_rise", "n", "median", "scatter",
                                            "peak_median"),
                  dtype=("U8", float, int, float, float, float))
    table["t_rise"].unit = u.s
    table["median"].description = "median (fitted - injected at that time) / injected"
    table["scatter"].description = "half the 16-84 % range of the same"
    table["peak_median"].description = "median (fitted - S_p) / S_p, detection nearest the peak"
    return table


def pointing_table(detections: Table) -> Table:
    """Median and 68th percentile of fitted-position offsets per band, also / FWHM, next to
    the paper's median."""
    rows = []
    for band in sorted(set(detections["bandpass"])) if len(detections) else []:
        off = np.asarray(detections["offset"][detections["bandpass"] == band], float) / ARCSEC
        fwhm = get_band(band).fwhm / ARCSEC
        med, p68 = np.median(off), np.percentile(off, 68.27)
        rows.append((band, len(off), med, p68, fwhm, med / fwhm, p68 / fwhm,
                     PAPER_POINTING_ARCSEC.get(band, np.nan)))
    table = Table(rows=rows or None, names=("band", "n", "median", "p68", "fwhm",
                                            "median_over_fwhm", "p68_over_fwhm",
                                            "paper_median"),
                  dtype=("U8", int, float, float, float, float, float, float))
    for name in ("median", "p68", "fwhm", "paper_median"):
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


def fitted_noise_table(folders: dict) -> Table:
    """Every candidate fitted on the noise-only data of the groups (``fitted_noise.ecsv``),
    with its band: the false-detection rate at any raised threshold."""
    parts = []
    for group, folder in folders.items():
        path = Path(folder) / "fitted_noise.ecsv"
        table = Table.read(path) if path.exists() else Table()
        if len(table):
            nan = np.full(len(table), np.nan)
            part = Table({"band": np.full(len(table), group.band),
                          "wafer_slot": np.full(len(table), group.wafer),
                          "snr_fit": np.asarray(table["snr_fit"], float)})
            for name in STATISTICS:
                part[name] = (np.asarray(table[name], float) if name in table.colnames
                              else nan)
            part["n_crossings"] = (np.asarray(table["n_crossings"], int)
                                   if "n_crossings" in table.colnames
                                   else np.ones(len(table), int))
            part["detected"] = np.asarray(table["detected"], bool)
            parts.append(part)
    return (vstack(parts) if parts else
            Table(names=("band", "wafer_slot", "snr_fit") + STATISTICS
                  + ("n_crossings", "detected"),
                  dtype=("U8", "U8", float) + (float,) * len(STATISTICS) + (int, bool)))


#: The coherent statistics a false-alarm budget can rank detections by (:mod:`.far_budget`).
STATISTICS = ("map_z", "coherent_snr")


def write_results(cfg, folder, flares, detections, folders, check=None, command="") -> Path:
    """Write every table and figure of one campaign, each table naming ``command``, the site
    config and the commit that ran; returns ``folder``."""
    eff = efficiency_table(flares)
    rms = noise_rms(folders)
    eff["tod_rms"] = [rms.get(b, np.nan) for b in eff["band"]]
    eff["tod_rms"].unit = u.mJy
    eff["tod_rms"].description = "median per-sample white noise of the band's detectors"
    statistic = cfg.far_statistic()
    # without a budget, backgrounds an earlier run of the config left are not read
    maxima, live = background_tables(folders if statistic else {})
    live["statistic"] = np.full(len(live), statistic or "", "U16")
    tables = dict(flares=flares, efficiency=eff,
                  flux_residuals=flux_residual_table(detections),
                  false_positives=false_positive_table(folders),
                  fitted_noise=fitted_noise_table(folders), full_check=check,
                  far_background=maxima if len(live) else None,
                  far_live=live if len(live) else None)
    meta = {"config_digest": cfg.digest(),
            "comments": [command, f"{stamp()}; site config "
                         f"{repository_path(cfg.preprocess)}"]}
    return write_tables(folder, tables, meta, cfg.seed)


#: What :func:`write_tables` is given (and :mod:`.combine` reads back), besides what it derives.
INPUT_TABLES = ("flares", "efficiency", "flux_residuals", "false_positives", "fitted_noise",
                "full_check", "far_background", "far_live")
#: Input tables a campaign may not have: the full-pipeline check, and the false-alarm
#: background (with a false-alarm budget only).
OPTIONAL_TABLES = ("full_check", "far_background", "far_live")


def write_tables(folder, tables: dict, meta: dict, seed=0) -> Path:
    """Derive thresholds, flux, pointing and equal-rate tables from ``tables`` (the
    :data:`INPUT_TABLES`) and write them all, with ``summary.md`` and the figures."""
    from so_transients.campaign.equal_rate import efficiency_at, equal_rate_thresholds
    from so_transients.campaign.figures import write_figures
    from so_transients.campaign.markdown import summary_markdown

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = dict(tables)
    eff, residuals, false = out["efficiency"], out["flux_residuals"], out["false_positives"]
    out["thresholds"] = threshold_table(eff, seed)
    out["flux_summary"] = flux_summary_table(residuals)
    out["pointing"] = pointing_table(residuals)
    fitted = out["fitted_noise"]
    hours = {str(r["band"]): float(r["wafer_hours"]) for r in false}
    out["equal_rate"] = equal_rate_thresholds(
        {b: np.asarray(fitted["snr_fit"][fitted["band"] == b]) for b in hours}, hours, seed=seed)
    cut = {str(r["band"]): float(r["snr_threshold"]) for r in out["equal_rate"]}
    out["efficiency_equal_rate"] = efficiency_at(out["flares"], residuals, cut)
    out["thresholds_equal_rate"] = threshold_table(out["efficiency_equal_rate"], seed)
    if out.get("far_live") is not None:
        out.update(far_budget_tables(out, hours, seed))
    for name, table in out.items():
        if table is not None:
            table.meta.update(meta)
            table.write(folder / f"{name}.ecsv", overwrite=True)
    (folder / "thresholds.md").write_text(thresholds_markdown(out["thresholds"], eff))
    (folder / "summary.md").write_text(summary_markdown(out))
    write_figures(folder, eff, residuals, out.get("noise_far"), hours)
    return folder


def far_budget_tables(tables: dict, wafer_hours: dict, seed=0) -> dict:
    """Detection at the paper's rate on the false-alarm background (:mod:`.far_budget`):
    ``far_budget`` (the Z per band and its check), ``efficiency_far``, ``thresholds_far`` and
    ``noise_far`` (the noise-only detections' far), each band ranked by the statistic
    ``far_live`` names for it (``map_z`` in coherent mode, ``coherent_snr`` in paper mode)."""
    from so_transients.campaign.equal_rate import efficiency_at
    from so_transients.campaign.far_budget import (
        budget_margin, budget_table, live_statistics, noise_far, pooled_backgrounds
    )

    statistics = live_statistics(tables["far_live"])
    backgrounds = pooled_backgrounds(tables["far_background"], tables["far_live"])
    budget = budget_table(backgrounds, tables["fitted_noise"], wafer_hours, statistics)
    matched = tables["flux_residuals"].copy(copy_data=False)
    # each detection against its own budget (a sweep stack's or a single crossing's)
    budgets = {str(r["band"]): (float(r["z_budget"]), float(r["z_stack_budget"]),
                                float(r["z_budget_chi2_failed"])) for r in budget}
    matched["budget_margin"] = budget_margin(matched, "bandpass", statistics, budgets)
    eff = efficiency_at(tables["flares"], matched, {band: 0.0 for band in backgrounds},
                        column="budget_margin")
    return dict(far_budget=budget, efficiency_far=eff,
                thresholds_far=threshold_table(eff, seed),
                noise_far=noise_far(backgrounds, tables["fitted_noise"], statistics))
