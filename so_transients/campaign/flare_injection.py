"""Injecting one flare into the filtered noise of an observation and searching for it.

The matched filter is linear once its noise weighting is fixed (:mod:`so_transients.campaign.noise_model`),
so a flare's S/N in a group is the noise-only S/N plus the filter applied to the flare's signal
alone. A crossing (one pass of the source over the group's footprint) touches the detectors for
about a second, so only a window of a few seconds around it is built: the signal is computed
there (the simulator's beam model), filtered with the group's noise model, added to the
memory-mapped noise S/N, and ``transient_find`` -> ``transient_cuts`` -> ``transient_fit`` run
on that window exactly as the site pipeline configures them (the fit's error scale fixed from
the noise-only group).

Each flare is injected alone: flares never interfere, which is what "not overlapping each
other" asks of the paper's injections, and every flare sees the same noise model.

With sweep stacking (``transient_find``'s ``stack_window``), the crossings within that window
centred on the flare's brightest are one window, from the first to the last (the union of
their detectors), so that the search stacks them as the site pipeline would; the others are
searched one by one as before. Such a window counts as one searched crossing.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from astropy.table import Table

from so_transients.common.bands import fwhm_to_sigma, get_band
from so_transients.campaign.noise_model import filtered_snr
from so_transients.campaign.matching import crossing_times
from so_transients.common.scan_geometry import constant_velocity, detector_pitch
from so_transients.sim.config import FlareConfig
from so_transients.sim.sources import (
    PointingContext, SourceCrossing, add_sources, draw_flares, source_crossings
)
from so_transients.campaign.search_steps import stack


def draw_cell_flares(cell, n, states, rng, placement="detector_at_peak", flare_eta=1.0
                     ) -> Table:
    """``n`` flares of ``cell`` at random peak times (anywhere in the constant-velocity part
    of the sweeps, as in the paper's section 5.1, up to the turnarounds; away from the ends
    of the observation) and positions (where a random detector of the band points then, or
    with ``placement="scan_area"`` at an independent random time of that kind, plus up to half
    a pixel pitch), for the observation of ``states`` (the band's groups, one obs); ``flare_eta``:
    the light curves' rise and decay power-law index."""
    first = states[0]
    xi = np.concatenate([s.xi for s in states])
    eta = np.concatenate([s.eta for s in states])
    names = np.concatenate([np.asarray(s.aman.dets.vals) for s in states])
    t = first.timestamps
    bore = first.aman.boresight
    scanning = constant_velocity(first.timestamps, bore.az, bore.el)
    edge = min(5.0 + cell.t_rise, 0.4 * (t[-1] - t[0]))   # light curves inside the observation
    scanning &= (t > t[0] + edge) & (t < t[-1] - edge)
    ctx = PointingContext(t, first.bore_q, scanning, xi, eta, names, detector_pitch(xi, eta))
    table = draw_flares(FlareConfig(n=n, s_peak_mjy=cell.s_peak, t_rise=cell.t_rise,
                                    eta_rise=flare_eta, eta_decay=flare_eta),
                        [cell.band], ctx, rng, placement)
    table["s_peak"][:] = cell.s_peak       # exact grid values (not exp(log(v)))
    table["t_rise"][:] = cell.t_rise
    table["t_decay"][:] = cell.t_rise
    return table


@dataclass
class CrossingResult:
    """What the search made of one flare in one group."""

    times: np.ndarray                  # ctime of each crossing's signal peak (for matching)
    n_searched: int = 0                # crossings searched
    n_skipped: int = 0                 # crossings too faint to search
    detections: Table = field(default_factory=Table)


def _runs(samples):
    """Split sorted sample indices into runs of consecutive samples."""
    breaks = np.flatnonzero(np.diff(samples) > 1) + 1
    return np.split(np.arange(len(samples)), breaks)


def _strip(state, track, reach):
    """Indices of the group's detectors passing within ``reach`` of the source's track (flat
    focal-plane distance, which over a wafer differs from the angle by < 1e-4 of it). The track
    is thinned to <= 65 points and ``reach`` widened by the largest gap between them."""
    step = max(1, len(track.xi) // 64)
    xi, eta = track.xi[::step], track.eta[::step]
    limit = reach + step * _track_step(track)
    d2 = (state.xi[:, None] - xi[None, :]) ** 2 + (state.eta[:, None] - eta[None, :]) ** 2
    return np.flatnonzero(d2.min(axis=1, initial=np.inf) <= limit**2)


def _track_step(track):
    """Largest angular step between consecutive samples of the track."""
    if len(track.xi) < 2:
        return 0.0
    return float(np.max(np.hypot(np.diff(track.xi), np.diff(track.eta))))


def _expected_snr(signal, sigma_amp):
    """Highest peak S/N any detector can expect from ``signal`` (dead ones, sigma 0: none)."""
    peak = signal.max(axis=1, initial=0.0)
    live = sigma_amp > 0
    return float(np.max(peak[live] / sigma_amp[live], initial=0.0))


def _run_window(state, track, run, pad, reach):
    """``(dets, lo, hi, [crossing])`` of one crossing (``run``: its indices in ``track``):
    the samples ``pad`` either side of it, the detectors within ``reach`` of its track, and
    the crossing with samples counted from ``lo``."""
    lo = max(int(track.samples[run[0]]) - pad, 0)
    hi = min(int(track.samples[run[-1]]) + pad + 1, len(state.timestamps))
    local = SourceCrossing(track.samples[run] - lo, track.xi[run], track.eta[run],
                           track.flux[run])
    return _strip(state, local, reach), lo, hi, [local]


def _stacked_runs(runs, window):
    """The crossings within ``window`` samples centred on the brightest (the most flux) as
    one window (the union of their detectors, their samples from the first to the last), so
    that ``transient_find``'s sweep stacking sees them together; the others as they are."""
    peak = [float(np.max(c[0].flux)) for *_, c in runs]
    centre = [0.5 * (lo + hi) for _, lo, hi, _ in runs]
    t0 = centre[int(np.argmax(peak))]
    inside = [abs(c - t0) <= window / 2 for c in centre]
    if sum(inside) < 2:
        return runs
    group = [r for r, keep in zip(runs, inside) if keep]
    lo = min(r[1] for r in group)
    merged = (np.unique(np.concatenate([r[0] for r in group])), lo, max(r[2] for r in group),
              [SourceCrossing(c.samples + (r[1] - lo), c.xi, c.eta, c.flux)
               for r in group for c in r[3]])
    return [merged] + [r for r, keep in zip(runs, inside) if not keep]


def injected_windows(state, track, stack_window, options) -> list:
    """The flare's signal (``track``: its samples in the group's footprint) as the standard
    steps leave it, a window per crossing (``stack_window`` s: the crossings stacked together,
    see the module doc), brightest first: ``(expected S/N, dets, lo, hi, signal)`` with
    ``signal`` (len(dets), hi - lo) in the data's units, as the detectors record it
    (:class:`~so_transients.campaign.noise.Response`) less what the PCA takes of it
    (:mod:`~so_transients.campaign.pca_response`)."""
    fs = state.model.sample_rate
    sigma = fwhm_to_sigma(get_band(state.group.band).fwhm)
    pad = int(round(options.window_pad * fs))
    runs = [_run_window(state, track, run, pad, options.strip_sigma * sigma)
            for run in _runs(track.samples)]
    if stack_window and len(runs) > 1:
        runs = _stacked_runs(runs, stack_window * fs)
    windows = []
    for dets, lo, hi, crossings in runs:
        signal = np.zeros((len(dets), hi - lo), np.float32)
        response = state.response
        add_sources(signal, response.xi[dets], response.eta[dets], crossings, sigma)
        response.observe(signal, dets, fs)
        if state.pca is not None:
            state.pca.apply(signal, dets, fs)
        windows.append((_expected_snr(signal, state.sigma_amp[dets]), dets, lo, hi, signal))
    windows.sort(key=lambda w: -w[0])
    return windows


def inject_flare(state, flare, search, options) -> CrossingResult:
    """Inject ``flare`` (a truth-table row) into one prepared group and search each crossing."""
    band = get_band(state.group.band)
    sigma = fwhm_to_sigma(band.fwhm)
    centre, radius = state.footprint
    tracks = source_crossings(state.timestamps, state.bore_q, [flare], centre, radius, sigma)
    if not tracks:   # never within the footprint plus the beam's reach: never crossed
        return CrossingResult(np.zeros(0))
    track = tracks[0]
    result = CrossingResult(crossing_times(state.timestamps, state.bore_q, state.xi, state.eta,
                                           flare, band.fwhm,
                                           track=(track.samples, track.xi, track.eta)))
    windows = injected_windows(state, track, search.stack_window, options)
    tables = []
    for rank, (expected, dets, lo, hi, signal) in enumerate(windows):
        limit = options.max_crossings is not None and rank >= options.max_crossings
        if expected < options.min_expected_snr or limit:
            result.n_skipped += 1
            continue
        # detectors whose injected S/N would stay below 1e-3 are left as pure noise
        rows = np.flatnonzero(signal.max(axis=1) > 1e-3 * state.sigma_amp[dets])
        extra = filtered_snr(state.model, dets[rows], signal[rows], pad=options.filter_pad)
        found = search.run(state.window(dets, lo, hi, extra, rows), state.group.obs_id)
        result.n_searched += 1
        if len(found):
            tables.append(found)
    if tables:
        result.detections = stack(tables)
    return result
