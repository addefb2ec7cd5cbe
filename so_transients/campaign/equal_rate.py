"""Thresholds compared at the paper's false-detection rate.

Our default detection threshold (fitted S/N >= 5) lets through more noise per wafer-band-hour
than the paper's search did (about 2 per hour over 24 MF wafer-bands and 1 per hour over 12
UHF wafer-bands: 0.08 per wafer-band-hour in both). A fair comparison of the 10/50/90 %
thresholds raises our threshold on the fitted S/N until the noise-only rate is the paper's.

The rate at a raised threshold comes from every candidate fitted on the noise-only data (at
any fitted S/N; ``fitted_noise.ecsv`` of each group): with a few wafer-band-hours there are
too few false detections above S/N 5 to count down to 0.08 per wafer-band-hour, so the tail of
the fitted S/N above ``x0`` is modelled as Gaussian-like, ``N(>x) = N(>x0) exp(-(x^2 - x0^2) /
2 s^2)``, with ``s^2`` its maximum-likelihood value ``mean(x^2 - x0^2) / 2`` (Gaussian noise
has ``N(>x)`` proportional to ``exp(-x^2 / 2) / x``, close to this with s = 1; correlated or
glitchy noise gives s > 1), and the threshold solved for. Its error is
bootstrapped over the candidates. The counts above the detection cut check the model
(``n_above_cut`` beside ``model_above_cut``); the threshold is never below that cut, and is
raised above every noise candidate when more of them than the paper's rate allows lie above
the model's threshold (outliers such as glitch residues, which a Gaussian-like tail misses).

Each flare is then detected at threshold ``x`` when one of its matched detections has
``snr_fit >= x``, and the efficiencies and thresholds are recomputed.
"""
from __future__ import annotations

import numpy as np
from astropy import units as u
from astropy.table import Table

from so_transients.significance.tail_model import model_count_above, tail_threshold
from so_transients.campaign.stats import binomial_interval

#: The paper's false-detection rate per wafer-band-hour (section 5.3: about 2 per hour over
#: 12 MF wafers x 2 bands, about 1 per hour over 6 UHF wafers x 2 bands).
PAPER_RATE_PER_WBH = {"f090": 2 / 24, "f150": 2 / 24, "f220": 1 / 12, "f280": 1 / 12}


def raised_threshold(snr, wafer_hours, target, x0=3.0, min_snr=5.0):
    """The threshold at the paper's rate: the tail model's, but never below the detection
    cut ``min_snr``, and above every measured noise candidate when more of them exceed the
    model's threshold than the target allows (outliers the Gaussian-like tail misses, such
    as glitch residues, are then not hidden by the model). With too few candidates above
    ``x0`` to model the tail, ``min_snr`` (or above the measured candidates passing it)."""
    snr = np.asarray(snr, float)
    x_model = tail_threshold(snr, wafer_hours, target, x0)[0]
    # too few noise candidates to model the tail: none of them reaches far, so the cut stays
    # where it is (raised above any measured one that passes it)
    x = max(x_model, min_snr) if np.isfinite(x_model) else min_snr
    above = snr[snr >= x]
    if len(above) > target * wafer_hours:
        x = float(above.max()) + 0.01
    return x


def equal_rate_thresholds(fitted, wafer_hours, x0=3.0, min_snr=5.0, n_boot=200,
                          seed=0) -> Table:
    """Per band: the fitted-S/N threshold at the paper's rate (:func:`raised_threshold`),
    with a bootstrap error, and the tail model's own threshold and scale.

    ``fitted``: {band: fitted S/N of every noise-only candidate}; ``wafer_hours``: {band: the
    noise-only wafer-band-hours they come from}."""
    rng = np.random.default_rng(seed)
    rows = []
    for band in sorted(fitted):
        snr = np.asarray(fitted[band], float)
        snr = snr[np.isfinite(snr)]
        hours, target = wafer_hours[band], PAPER_RATE_PER_WBH.get(band, np.nan)
        x_model, scale, n0 = tail_threshold(snr, hours, target, x0)
        x = raised_threshold(snr, hours, target, x0, min_snr)
        boot = [raised_threshold(rng.choice(snr, len(snr)), hours, target, x0, min_snr)
                for _ in range(n_boot)] if len(snr) else [x]
        basis = "tail model" if np.isfinite(x_model) else f"fewer than 5 above {x0:g}"
        rows.append((band, hours, target, len(snr), n0, scale, x_model, x, basis,
                     float(np.nanstd(boot)), int(np.sum(snr >= min_snr)),
                     model_count_above(min_snr, snr, x0)))
    table = Table(rows=rows or None,
                  names=("band", "wafer_hours", "target_per_wbh", "n_fitted", "n_tail",
                         "tail_scale", "snr_model", "snr_threshold", "basis",
                         "snr_threshold_err", "n_above_cut", "model_above_cut"),
                  dtype=("U8", float, float, int, int, float, float, float, "U32", float, int,
                         float))
    table["wafer_hours"].unit = u.hour
    table["target_per_wbh"].unit = 1 / u.hour
    table.meta.update(x0=x0, min_snr=min_snr)
    return table


def efficiency_at(flares: Table, matched: Table, band_threshold: dict,
                  column="snr_fit") -> Table:
    """The efficiency table (as :func:`.report.efficiency_table`) with a flare detected only
    when one of its ``matched`` detections reaches its band's threshold on ``column`` (the
    fitted S/N; ``map_z`` for the coherent Z)."""
    key = lambda t, band: list(zip(t["obs_id"], t[band], np.asarray(t["t_rise"], float),
                                   np.asarray(t["s_peak"], float), t["source_id"]))
    best = {}
    values = (np.asarray(matched[column], float) if column in matched.colnames
              else np.full(len(matched), np.nan))
    for k, snr in zip(key(matched, "bandpass"), values):
        best[k] = max(best.get(k, -np.inf), snr)
    rows = []
    cells = sorted({(str(b), float(t), float(s)) for b, t, s in
                    zip(flares["band"], flares["t_rise"], flares["s_peak"])})
    keys = key(flares, "band")
    for band, t_rise, s_peak in cells:
        sel = [i for i, k in enumerate(keys) if k[1:4] == (band, t_rise, s_peak)]
        x = band_threshold.get(band, np.nan)
        k_det = sum(best.get(keys[i], -np.inf) >= x for i in sel)
        eff, lo, hi = binomial_interval(k_det, len(sel))
        rows.append((band, t_rise, s_peak, len(sel), int(k_det), float(eff), float(lo),
                     float(hi)))
    table = Table(rows=rows, names=("band", "t_rise", "s_peak", "injected", "detected",
                                    "efficiency", "eff_lo", "eff_hi"),
                  dtype=("U8", float, float, int, int, float, float, float))
    table["t_rise"].unit, table["s_peak"].unit = u.s, u.mJy
    return table
