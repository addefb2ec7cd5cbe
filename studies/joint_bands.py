"""Both bands of a wafer searched together against each band alone, at one false-alarm rate
per wafer-hour (issue: both bands together).

    python studies/joint_bands.py studies/configs/joint_bands.yaml [-o OUT]

The noise-only groups are those of a campaign (the config's ``campaign``: one MF wafer,
f090 and f150, simulated, preprocessed and filtered by the campaign machinery). On each
wafer-hour this measures three backgrounds with the same code
(:func:`so_transients.significance.joint_far.joint_background`: time slides and the
sign-inverted data): the joint statistic J over both bands, and each band's coherent Z
alone. Thresholds at the same rate per wafer-hour: J at ``rate``, each band at ``rate / 2``
(a flare is detected by the single-band search when either band detects it).

Flares of each ``t_rise`` peaking as they cross a random detector, of each spectral index
(flux ``S (nu / 93 GHz)^alpha``, ``S`` the grid's value at 93 GHz), are injected through the
noise model of each band's filter (:mod:`so_transients.campaign.noise_model`) into the
noise-only S/N, and each statistic is read at the flare's crossing (the highest value within
one row and two beam-crossing times of it). Written to the output folder:
``efficiency.ecsv`` (per rise time, index, flux and search), ``thresholds.ecsv`` (50 and
90 % with bootstrap errors), ``backgrounds.ecsv`` (live times, thresholds and the
noise-only data's own maxima above them, glitch-vetoed as ``transient_find`` vetoes: the
rate's check) and ``thresholds.png`` (the 90 % threshold against the flare's duration).
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib
import numpy as np
from astropy.table import Table
from tqdm import tqdm

from so_transients.campaign.config import load_campaign, read_study_config
from so_transients.campaign.noise import GroupState
from so_transients.campaign.noise_model import filtered_snr
from so_transients.campaign.provenance import stamp
from so_transients.campaign.run import prepare_noise
from so_transients.campaign.stats import thresholds
from so_transients.coherent.config import find_settings
from so_transients.coherent.joint import (
    DEFAULT_INDICES, band_scans, joint_map, joint_maxima
)
from so_transients.coherent.statistic import coherent_map, window_max
from so_transients.coherent.sweep_stack import map_cell
from so_transients.common.bands import fwhm_to_sigma, get_band
from so_transients.common.scan_geometry import constant_velocity, detector_pitch
from so_transients.detect.find import group_scans
from so_transients.sim.config import FlareConfig
from so_transients.sim.sources import PointingContext, add_sources, draw_flares, source_crossings
from so_transients.significance.far import SignificanceConfig
from so_transients.significance.joint_far import joint_background

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


@dataclass
class JointBandsConfig:
    output: str
    campaign: str                       # campaign config of the noise-only groups
    rate: float = 0.16                  # false alarms per wafer-hour (both bands)
    spectral_indices: list = field(default_factory=lambda: [-1.0, 0.0, 2.0])
    s_peak_mjy: list = field(default_factory=lambda: [100.0, 200.0, 300.0])   # at 93 GHz
    t_rise: list = field(default_factory=lambda: [5.0])    # s
    n_flares: int = 40                  # flares per spectral index (every flux)
    n_slides: int = 100                 # time slides per scan of each background
    statistic_indices: list = field(default_factory=lambda: list(DEFAULT_INDICES))
    seed: int = 38


SEARCHES = ("joint", "single")


@dataclass
class Search:
    """One background run: the bands it combines, its background and each scan's maps'
    rows, geometries, scales and coefficients (what an injection's map needs)."""

    bands: tuple
    background: object = None
    scans: dict = field(default_factory=dict)
    maxima: list = field(default_factory=list)     # the noise-only data's own maxima


def run_background(states, bands, scan, sig: SignificanceConfig, vetoes_share,
                   instant_share, indices):
    search = Search(tuple(bands))
    st = [states[b] for b in bands]
    rows = [np.flatnonzero(s.sigma_amp > 0) for s in st]
    scans = band_scans(bands, [s.snr for s in st], rows, [s.xi[r] for s, r in zip(st, rows)],
                       [s.eta[r] for s, r in zip(st, rows)],
                       [s.sigma_amp[r] for s, r in zip(st, rows)],
                       [beam_sigma(b) for b in bands], st[0].timestamps, st[0].bore_q, scan)

    def visit(js):
        search.scans[js.first] = dict(
            rows=js.rows, geometries=[s.geometry for s in js.scans],
            scales=[m.scale for m in js.maps], coefficients=js.coefficients,
            dets=rows, nsamp=js.j.shape[1], window=js.window)
        r, s = joint_maxima(js.scans, js.maps, js.rows, js.coefficients, js.j, js.best,
                            sig.background_floor, js.window, vetoes_share, instant_share)
        search.maxima.extend(js.j[r, s])

    n_scans = len(np.unique(scan[scan >= 0]))
    search.background = joint_background(
        tqdm(scans, total=n_scans, desc=f"background {'+'.join(bands)}"), sig, indices,
        vetoes_share, visit)
    return search


def beam_sigma(band):
    return fwhm_to_sigma(get_band(band).fwhm)


def unit_flare_snr(state, flare, band, pad_s, filter_pad):
    """``(lo, hi, dets, snr)``: the filtered S/N of ``flare`` at 1 mJy (93 GHz, scaled by its
    index) in the band over the crossing containing its peak, ``pad_s`` either side."""
    sigma = beam_sigma(band)
    centre, radius = state.footprint
    tracks = source_crossings(state.timestamps, state.bore_q, [flare], centre, radius, sigma)
    if not tracks:
        return None
    track = tracks[0]
    peak = int(np.searchsorted(state.timestamps, flare["t_peak"]))
    breaks = np.flatnonzero(np.diff(track.samples) > 1) + 1
    runs = np.split(np.arange(len(track.samples)), breaks)
    run = min(runs, key=lambda r: np.min(np.abs(track.samples[r] - peak)))
    pad = int(round(pad_s * state.model.sample_rate))
    lo = max(int(track.samples[run[0]]) - pad, 0)
    hi = min(int(track.samples[run[-1]]) + pad + 1, len(state.timestamps))
    dets = np.flatnonzero(state.sigma_amp > 0)
    signal = np.zeros((len(dets), hi - lo), np.float32)
    crossing = type(track)(track.samples[run] - lo, track.xi[run], track.eta[run],
                           track.flux[run])
    add_sources(signal, state.response.xi[dets], state.response.eta[dets], [crossing], sigma)
    state.response.observe(signal, dets, state.model.sample_rate)
    near = np.flatnonzero(signal.max(axis=1) > 1e-4)
    snr = np.zeros_like(signal)
    snr[near] = filtered_snr(state.model, dets[near], signal[near], pad=filter_pad)
    return lo, hi, dets, snr


def statistic_at(search: Search, states, parts, s0, flare, lo, hi, scan, peak_window):
    """The highest value of the search's statistic within one row and ``peak_window``
    crossing times of the flare's crossing, with the flare at ``s0`` mJy (93 GHz)."""
    k = scan[int(np.searchsorted(states[search.bands[0]].timestamps, flare["t_peak"]))]
    first = int(np.flatnonzero(scan == k)[0])
    info = search.scans.get(first)
    if info is None:
        return np.nan
    lo, hi = max(lo, first), min(hi, first + info["nsamp"])
    zs = []
    for b, g, scale, rows in zip(search.bands, info["geometries"], info["scales"],
                                 info["dets"]):
        st = states[b]
        wlo, whi, dets, unit = parts[b]
        snr = np.nan_to_num(np.asarray(st.snr[rows, lo:hi], float))
        # the flare's S/N on the same detectors (``dets`` are ``rows``), where both windows
        # overlap
        a, b_ = max(lo, wlo), min(hi, whi)
        if b_ > a:
            snr[np.searchsorted(rows, dets), a - lo:b_ - lo] += s0 * unit[:, a - wlo:b_ - wlo]
        z, _ = coherent_map(snr, g, info["rows"], beam_sigma(b), st.sigma_amp[rows],
                            np.ones(len(rows), bool), with_flux=False, finite=True)
        zs.append(z / scale)
    j, _ = joint_map(np.stack(zs), info["coefficients"])
    g = info["geometries"][0]
    st = states[search.bands[0]]
    row, t0, _ = map_cell(g, info["rows"], lo, st.bore_q, flare["ra"], flare["dec"],
                          int(np.searchsorted(st.timestamps, flare["t_peak"])))
    half = int(peak_window * info["window"])
    return float(window_max(j, [row], [t0], 1, half)[0])


def draw(states, cfg, t_rise, alpha, rng):
    st = states["f090"]
    bore = st.aman.boresight
    t = st.timestamps
    scanning = constant_velocity(t, bore.az, bore.el)
    edge = 5.0 + t_rise
    scanning &= (t > t[0] + edge) & (t < t[-1] - edge)
    ctx = PointingContext(t, st.bore_q, scanning, st.xi, st.eta,
                          np.asarray(st.aman.dets.vals), detector_pitch(st.xi, st.eta))
    table = draw_flares(FlareConfig(n=cfg.n_flares, s_peak_mjy=1.0, t_rise=t_rise,
                                    spectral_index=alpha), ["f090", "f150"], ctx, rng)
    return table


def inject(states, searches, thr, cfg, camp, sig, scan, t_rise, alpha, rng, labels):
    """Efficiency rows of ``cfg.n_flares`` flares of ``t_rise`` and index ``alpha`` at each
    of the grid's fluxes, for each search."""
    rows = []
    flares = draw(states, cfg, t_rise, alpha, rng)
    for fid in tqdm(np.unique(flares["source_id"]), desc=f"t_r {t_rise:g} s, index {alpha:+g}"):
        per_band = {r["band"]: r for r in flares[flares["source_id"] == fid]}
        parts = {b: unit_flare_snr(states[b], per_band[b], b, 3.0, camp.injection.filter_pad)
                 for b in per_band}
        if any(v is None for v in parts.values()):
            continue
        lo = min(v[0] for v in parts.values())
        hi = max(v[1] for v in parts.values())
        for s0 in cfg.s_peak_mjy:
            found = {name: any(statistic_at(s, states, parts, s0, per_band["f090"], lo, hi,
                                            scan, sig.peak_window) >= thr[s.bands]
                               for s in runs)
                     for name, runs in searches.items()}
            rows.append(dict(**labels, t_rise=t_rise, spectral_index=alpha, s_peak=s0,
                             flare=int(fid), **found))
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("config", type=Path)
    p.add_argument("-o", "--out", type=Path)
    args = p.parse_args(argv)
    cfg = read_study_config(JointBandsConfig, args.config, args.out)
    camp = load_campaign(cfg.campaign)
    out = cfg.output
    out.mkdir(parents=True, exist_ok=True)
    folders, _ = prepare_noise(camp, out / "campaign")
    _, search_steps = camp.pipeline_steps()
    calc = next(s.get("calc", {}) for s in search_steps if s["name"] == "transient_find")
    find, coherent = find_settings(calc)
    sig = SignificanceConfig(n_slides=cfg.n_slides, seed=cfg.seed)
    by_unit = {}
    for group, folder in folders.items():
        by_unit.setdefault((group.obs_id, group.wafer), {})[group.band] = GroupState.load(
            group, folder, search_steps)
    rows_eff, rows_bg = [], []
    rng = np.random.default_rng(cfg.seed)
    for (obs, wafer), states in sorted(by_unit.items()):
        st = states["f090"]
        scan, _ = group_scans(st.timestamps, st.aman.boresight.az, st.aman.boresight.el, find)
        searches = {
            "joint": [run_background(states, ("f090", "f150"), scan, sig,
                                     coherent.max_single_share, coherent.max_instant_share,
                                     cfg.statistic_indices)],
            "single": [run_background(states, (b,), scan, sig, coherent.max_single_share,
                                      coherent.max_instant_share, cfg.statistic_indices)
                       for b in ("f090", "f150")]}
        thr = {}
        for name, runs in searches.items():
            rate = cfg.rate / len(runs)
            for s in runs:
                bg = s.background
                thr[s.bands] = bg.threshold(rate)
                rows_bg.append(dict(obs_id=obs, wafer=wafer, search=name,
                                    bands="+".join(s.bands), rate=rate,
                                    threshold=thr[s.bands], slide_hours=bg.slide_hours,
                                    data_hours=bg.data_hours, n_slide_maxima=len(bg.slides),
                                    n_inverted_maxima=len(bg.inverted),
                                    n_data_above=int(np.sum(np.asarray(s.maxima)
                                                            >= thr[s.bands]))))
                print(rows_bg[-1])
        for t_rise in cfg.t_rise:
            for alpha in cfg.spectral_indices:
                rows_eff += inject(states, searches, thr, cfg, camp, sig, scan, t_rise, alpha,
                                   rng, dict(obs_id=obs, wafer=wafer))
    provenance = [f"python studies/joint_bands.py {args.config}",
                  f"{stamp()}; campaign {cfg.campaign}"]
    report(cfg, out, Table(rows=rows_eff), Table(rows=rows_bg), provenance)


def report(cfg, out, flares, backgrounds, provenance=()):
    """The tables and the figure; ``provenance``: comment lines every table carries (the
    command, commit and date)."""
    backgrounds.meta["comments"] = list(provenance)
    backgrounds.write(out / "backgrounds.ecsv", overwrite=True)
    eff, thr = [], []
    for t_rise in cfg.t_rise:
        for alpha in cfg.spectral_indices:
            sel = flares[(flares["spectral_index"] == alpha) & (flares["t_rise"] == t_rise)]
            s = np.array(sorted(set(sel["s_peak"])))
            for name in SEARCHES:
                k = np.array([np.sum(sel[name][sel["s_peak"] == v]) for v in s])
                n = np.array([np.sum(sel["s_peak"] == v) for v in s])
                for v, kk, nn in zip(s, k, n):
                    eff.append(dict(t_rise=t_rise, spectral_index=alpha, search=name, s_peak=v,
                                    k=kk, n=nn, efficiency=kk / nn))
                levels = thresholds(s, k, n, levels=(0.5, 0.9))
                thr.append(dict(t_rise=t_rise, spectral_index=alpha, search=name,
                                s50=levels[0.5][0], s50_err=levels[0.5][1],
                                s90=levels[0.9][0], s90_err=levels[0.9][1]))
    eff, thr = Table(rows=eff), Table(rows=thr)
    for table in (eff, thr):
        table["t_rise"].unit = "s"
        table.meta["comments"] = list(provenance)
    for name in ("s_peak", "s50", "s50_err", "s90", "s90_err"):
        (eff if name == "s_peak" else thr)[name].unit = "mJy"
    eff.write(out / "efficiency.ecsv", overwrite=True)
    thr.write(out / "thresholds.ecsv", overwrite=True)
    print(backgrounds)
    thr.pprint(max_lines=-1, max_width=-1)
    plot(cfg, thr, out / "thresholds.png")
    print(f"written {out}")


def plot(cfg, thr, path):
    """The 90 % threshold against the flare's duration (t_r + t_d = 2 t_r), one panel per
    spectral index, both searches."""
    fig, axes = plt.subplots(1, len(cfg.spectral_indices),
                             figsize=(3.6 * len(cfg.spectral_indices), 3.3), sharey=True)
    axes = np.atleast_1d(axes)
    for ax, alpha in zip(axes, cfg.spectral_indices):
        for name, style in zip(SEARCHES, ("-o", "--s")):
            sel = thr[(thr["spectral_index"] == alpha) & (thr["search"] == name)]
            ax.errorbar(2 * np.asarray(sel["t_rise"]), sel["s90"], sel["s90_err"], fmt=style,
                        ms=3, capsize=2,
                        label="both bands jointly" if name == "joint" else "each band alone")
        ax.set_xscale("log")
        ax.set_title(f"spectral index {alpha:+g}", fontsize=9)
        ax.set_xlabel("flare duration 2 t_r (s)")
    axes[0].set_ylabel("90 % threshold at 93 GHz (mJy)")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"one MF wafer (f090 + f150), {cfg.rate:g} false alarms per wafer-hour",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
