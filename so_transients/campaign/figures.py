"""The campaign's figures, like the reference paper's (its figures 7-10).

* ``efficiency.png``: efficiency vs S_p per band, one line per t_r with 68 % intervals, the
  10 / 50 / 90 % levels as guides and the per-sample noise rms of the band marked;
* ``flux_residuals.png``: fractional (fitted - injected) / injected flux vs S_p per band
  (injected flux at the detection's time), medians per t_r;
* ``pointing.png``: distribution of fitted-position offsets per band, FWHM and sigma marked;
* ``far_calibration.png`` (with a false-alarm budget): the noise-only detections with ``far <= x``
  against ``x`` times the live time;
* :func:`plot_sensitivity_timescale` (``studies/sensitivity_timescale.py``): the 90 % threshold
  of several campaigns against the flare's duration, one panel per band.
"""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from so_transients.common.angles import ARCSEC  # noqa: E402
from so_transients.common.bands import fwhm_to_sigma, get_band  # noqa: E402
from so_transients.campaign.stats import LEVELS  # noqa: E402


def _panels(bands):
    """One panel per band, in one row (two rows of two for four bands, like the paper's)."""
    n = max(len(bands), 1)
    rows = 2 if n == 4 else 1
    cols = n // rows
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.2 * rows), squeeze=False)
    return fig, axes.ravel()


def _by_rise(rows):
    """(index, t_r, colour, rows of that t_r) for each rise time in ``rows``, shortest first."""
    rises = sorted(set(rows["t_rise"]))
    colors = plt.cm.viridis(np.linspace(0, 0.9, len(rises)))
    for k, (t_rise, color) in enumerate(zip(rises, colors)):
        yield k, t_rise, color, rows[rows["t_rise"] == t_rise]


def _save(fig, path):
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_efficiency(path, eff):
    """Efficiency curves per band; the band's TOD rms (``eff["tod_rms"]``) marked."""
    bands = sorted(set(eff["band"]))
    noise_rms = ({str(b): float(r) for b, r in zip(eff["band"], eff["tod_rms"])}
                 if "tod_rms" in eff.colnames else {})
    fig, axes = _panels(bands)
    for ax, band in zip(axes, bands):
        for _, t_rise, color, row in _by_rise(eff[eff["band"] == band]):
            row.sort("s_peak")
            e = np.asarray(row["efficiency"])
            ax.errorbar(row["s_peak"], e, yerr=[e - row["eff_lo"], row["eff_hi"] - e],
                        color=color, marker="o", ms=3, capsize=2, label=f"$t_r$ = {t_rise:g} s")
        for level in LEVELS:
            ax.axhline(level, color="0.6", ls=":", lw=0.8)
        if band in noise_rms:
            ax.axvline(noise_rms[band], color="k", ls="--", lw=0.8,
                       label=f"TOD rms {noise_rms[band]:.0f} mJy")
        ax.set(xlabel="injected peak flux $S_p$ (mJy)", ylabel="detection efficiency",
               title=band, ylim=(-0.03, 1.03))
        ax.legend(fontsize=7, loc="lower right")
    _save(fig, path)


def plot_flux_residuals(path, residuals):
    bands = sorted(set(residuals["bandpass"])) if len(residuals) else []
    fig, axes = _panels(bands)
    for ax, band in zip(axes, bands):
        mine = residuals[residuals["bandpass"] == band]
        n_rises = len(set(mine["t_rise"]))
        for k, t_rise, color, row in _by_rise(mine):
            s = np.asarray(row["s_peak"], float)
            r = np.asarray(row["residual"], float)
            jitter = 1 + 0.015 * (k - n_rises / 2)
            ax.plot(s * jitter, r, ".", color=color, alpha=0.25, ms=3)
            grid = np.unique(s)
            med = [np.nanmedian(r[s == g]) for g in grid]
            ax.plot(grid * jitter, med, "-o", color=color, ms=4, label=f"$t_r$ = {t_rise:g} s")
        ax.axhline(0, color="k", lw=0.8)
        ax.set(xlabel="injected peak flux $S_p$ (mJy)",
               ylabel="(fitted - injected) / injected flux", title=band, ylim=(-1, 2))
        ax.legend(fontsize=7)
    _save(fig, path)


def plot_pointing(path, residuals):
    bands = sorted(set(residuals["bandpass"])) if len(residuals) else []
    fig, axes = _panels(bands)
    for ax, band in zip(axes, bands):
        off = np.asarray(residuals["offset"][residuals["bandpass"] == band], float) / ARCSEC
        fwhm = get_band(band).fwhm / ARCSEC
        ax.hist(off, bins=np.linspace(0, 30, 31), color="teal", alpha=0.8)
        ax.axvline(np.median(off), color="k", label=f"median {np.median(off):.1f}\"")
        ax.axvline(fwhm, color="0.4", ls="--", label=f"FWHM {fwhm:.0f}\"")
        ax.axvline(fwhm_to_sigma(fwhm), color="0.4", ls=":", label=f"beam sigma {fwhm_to_sigma(fwhm):.0f}\"")
        ax.set(xlabel="fitted - true position (arcsec)", ylabel="detections", title=band)
        ax.legend(fontsize=7)
    _save(fig, path)


def plot_far_calibration(path, noise_far, wafer_hours):
    """Per band: the number of noise-only detections with ``far <= x`` against ``x`` times
    the band's wafer-band-hours (calibrated: on the line, within its Poisson band)."""
    bands = sorted(set(np.asarray(noise_far["band"]).astype(str)))
    fig, axes = _panels(bands)
    for ax, band in zip(axes, bands):
        far = np.sort(np.asarray(noise_far["far"][noise_far["band"] == band], float))
        far = far[np.isfinite(far) & (far > 0)]
        hours = wafer_hours[band]
        x = np.logspace(np.log10(max(far.min(), 1e-3) / 3), np.log10(far.max() * 3), 200) \
            if len(far) else np.logspace(-2, 3, 200)
        expected = x * hours
        ax.fill_between(x, np.maximum(expected - np.sqrt(expected), 0.1),
                        expected + np.sqrt(expected), color="0.85", label="x x live time ± 1σ")
        ax.plot(x, expected, color="0.4", lw=0.8)
        ax.step(far, np.arange(1, len(far) + 1), where="post", color="C3",
                label=f"noise-only detections ({hours:.1f} wafer-band-h)")
        ax.set(xscale="log", yscale="log", ylim=(0.5, None), title=band,
               xlabel="far x (per wafer-band-hour)", ylabel="detections with far <= x")
        ax.legend(fontsize=7, loc="upper left")
    _save(fig, path)


def write_figures(folder, eff, residuals, noise_far=None, wafer_hours=None):
    plot_efficiency(folder / "efficiency.png", eff)
    plot_flux_residuals(folder / "flux_residuals.png", residuals)
    plot_pointing(folder / "pointing.png", residuals)
    if noise_far is not None and len(noise_far):
        plot_far_calibration(folder / "far_calibration.png", noise_far, wafer_hours)


def plot_sensitivity_timescale(path, curves: dict, note=""):
    """:func:`sensitivity_timescale_figure` written to ``path``."""
    fig = sensitivity_timescale_figure(curves, note)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def sensitivity_timescale_figure(curves: dict, note=""):
    """The 90 % threshold (``s90`` +- ``s90_err``, mJy) against the flare's duration
    (2 t_r: rise and decay), one panel per band (in the order the curves first name them),
    one line per campaign, in one colour and style on every panel: ``curves`` maps a label
    to its ``thresholds*.ecsv`` table (:func:`~so_transients.campaign.report.
    threshold_table`). ``note``: lines under the panels (the false-alarm rate)."""
    bands = list(dict.fromkeys(str(b) for t in curves.values() for b in t["band"]))
    fig, axes = _panels(bands)
    styles = ["o-", "s--", "^-.", "d:", "v-", "x--"]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    top = 0.0
    for ax, band in zip(axes, bands):
        for k, (label, table) in enumerate(curves.items()):
            rows = table[table["band"] == band]
            rows = rows[np.isfinite(np.asarray(rows["s90"], float))]
            if not len(rows):
                continue
            rows.sort("t_rise")
            ax.errorbar(2 * np.asarray(rows["t_rise"], float), rows["s90"], yerr=rows["s90_err"],
                        fmt=styles[k % len(styles)], color=colors[k % len(colors)], ms=4,
                        capsize=2, label=label)
            top = max(top, float(np.max(np.asarray(rows["s90"]) + np.asarray(rows["s90_err"]))))
        ax.set(xscale="log", xlabel="flare duration $2 t_r$ (s)",
               ylabel="90 % detection threshold $S_p$ (mJy)", title=band)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    left = min(ax.get_xlim()[0] for ax in axes)
    right = max(ax.get_xlim()[1] for ax in axes)
    for ax in axes:                         # one scale: the panels compare at a glance
        ax.set_ylim(0, 1.05 * top)
        ax.set_xlim(left, right)
    lines = note.count("\n") + 1 if note else 0
    fig.tight_layout(rect=(0, 0.03 * lines, 1, 1))
    if note:
        fig.text(0.5, 0.01, note, ha="center", va="bottom", fontsize=8)
    return fig
