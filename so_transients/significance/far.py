"""A false-alarm rate for every candidate of a group, from time slides of its own data.

For each scan of each band of a group, the coherent statistic Z of every sky position the
wafer crosses (:mod:`so_transients.coherent.statistic`) is computed on the filtered S/N as it is (the
candidates' statistic: the highest Z within one row and ``peak_window`` beam-crossing times of
the candidate's position and crossing time) and on ``n_slides`` time slides of it (each
detector's stream shifted cyclically within the scan by a random offset, at least
``min_slide_s``, alike for the detectors of one of ``slide_groups`` random groups: noise and
glitches keep their statistics, a real source no longer lines up; the groups let the slides
share their sums, and the data's own maxima from ``slide_gate`` are gated out of what is
slid, see :mod:`so_transients.significance.slide_groups`).
The slides' local maxima are the background (those one detector makes alone, more than
``max_single_share`` of their sum, are left out: a slide scatters a bright source's own
spikes, and a glitch's, into such maxima); their live time is ``n_slides`` times the time
searched. A slide's maxima are counted from ``slide_floor`` (below it, rates are high enough
for the sign-inverted data's own live time to resolve them) and found coarse to fine
(:mod:`so_transients.significance.slide_maxima`) without summing the whole map. Each map is normalized
by its own robust standard deviation: residual atmosphere correlates neighbouring detectors,
which widens the data's Z (measured 1.19 on 30 minutes of simulated f090) but not the
slides', whose shifts break the correlation. Even in units of their own spread the data's
tail is heavier: ``studies/far_calibration.py`` finds ``far`` low by a factor of 1.3-2.6
at Z = 3.5-5, so read it as a lower bound. A candidate's ``far`` is the rate, per hour of
this wafer-band, of background maxima at least as large as its Z.

Every background maximum is also put to ``transient_find``'s chi-squared test
(:mod:`so_transients.coherent.crossing_chi2`): a candidate whose own maximum passes it is ranked
among the background maxima that pass it, one that fails among all of them.

A sweep stack (:mod:`so_transients.coherent.sweep_stack`) is ranked among stacks: the sign-inverted
maps' stacks over the data's live time, and stack slides over ``n_slides`` times it (the
scans' maps moved along their scans against each other, :mod:`so_transients.significance.stack_slides`).

Only the cheap statistic is repeated: the slides reuse the filtered S/N, never the filter.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from so_transients.coherent.statistic import (
    CrossingGeometry, coherent_map, crossing_geometry, false_alarm_rate, finite_snr,
    largest_share, local_maxima, fill_edges, measured_scale, row_members, row_offsets,
    row_weights, term_shares, window_max
)
from so_transients.common.scan_geometry import sample_rate as rate_of  # (``sample_rate``: Hz)
from so_transients.common.step_config import ConfigError, non_negative, positive, share, setting
from so_transients.significance.slide_groups import (
    gate_maxima, group_offsets, group_sum, partial_maps, scan_groups
)
from so_transients.significance.slide_maxima import SlideSearch
from so_transients.coherent.vetoes import Vetoes
from so_transients.significance.stack_slides import slid_stacks
from so_transients.coherent.sweep_stack import (
    ScanMap, StackSettings, inverted_stacks, map_cell, map_seeds, stack_at
)
from so_transients.significance.tail_model import model_count_above


@dataclass
class SignificanceConfig:
    n_slides: int | None = setting(
        100, "",
        "time slides per scan: background live time / data's (0: none, far from the sign-inverted data "
        "alone; null: as many as max_far needs, see slides_for)")
    min_slide_s: float = setting(2.0, "s", "every detector is shifted at least this far")
    slide_groups: int = setting(
        4, "",
        "detectors slid alike in this many random groups (0: each its own offset, about 4x the cost at f090)")
    slide_gate: float = setting(
        6.0, "Z",
        "grouped slides: the data's maxima from this Z (real sources) are gated out of what is slid")
    row_step: float = setting(0.8, "beam sigma", "beam sigmas between rows of positions")
    background_floor: float = setting(3.0, "Z", "background maxima counted from this Z")
    slide_floor: float = setting(
        4.5, "Z",
        "slides' maxima counted from this Z (below it, far rests on the sign-inverted data, which resolves "
        "it)")
    peak_window: float = setting(2.0, "beam-crossing times", "searched around a candidate")
    max_single_share: float = setting(
        0.5, "",
        "background maxima one detector makes more than this share of are left out")
    max_far: float | None = setting(
        None, "1 / h",
        "candidates with a false-alarm rate (per wafer-band-hour) above this are not detected; null: far is "
        "reported, not cut")
    seed: int = setting(0, "", "seed of the time slides' random offsets and groups")
    tail_from: float | None = setting(3.5, "Z", "inverted data's maxima modelled from this Z; null: off")
    sidelobe_window: float = setting(
        1.0, "s",
        "sign-inverted maxima this close to a data maximum and max_opposite_ratio times higher are "
        "its filter sidelobe, left out of the background")
    max_opposite_ratio: float = setting(
        2.0, "",
        "sign-inverted maxima within sidelobe_window of a data maximum and this many times higher are its "
        "filter sidelobe, left out of the background")

    def __post_init__(self):
        self.slide_groups = int(self.slide_groups)
        if self.n_slides is None and self.max_far is None:
            raise ConfigError("transient_significance: n_slides: null (as many as max_far "
                              "needs) requires max_far")
        for key in ("n_slides", "slide_groups"):
            if (getattr(self, key) or 0) < 0:
                raise ConfigError(f"transient_significance: {key} must be 0 or more, got "
                                  f"{getattr(self, key)}")
        positive("transient_significance", min_slide_s=self.min_slide_s, row_step=self.row_step,
                 background_floor=self.background_floor, slide_floor=self.slide_floor,
                 slide_gate=self.slide_gate, peak_window=self.peak_window,
                 max_far=self.max_far, tail_from=self.tail_from,
                 sidelobe_window=self.sidelobe_window,
                 max_opposite_ratio=self.max_opposite_ratio)
        share("transient_significance", max_single_share=self.max_single_share)
        non_negative("transient_significance", seed=self.seed)


    def slides_for(self, searched_hours) -> int:
        """The number of time slides for a group searched over ``searched_hours``: ``n_slides``
        as set, or for ``n_slides: null`` enough that the slides' live time is at least
        ``0.55 / max_far`` hours (a candidate above every slide maximum then has
        ``far_slides`` = 0.5 / live, 10 % below ``max_far``), and at least 100."""
        if self.n_slides is not None:
            return self.n_slides
        if not searched_hours > 0:
            return 100
        return max(100, int(np.ceil(0.55 / (self.max_far * searched_hours) - 1e-9)))


@dataclass
class ScanMaps:
    """What one scan of one band gives: its geometry, the map, the background maxima."""

    first: int                       # first sample of the scan in the group
    geometry: CrossingGeometry
    rows: np.ndarray
    z: np.ndarray                    # (nrow, nsamp) unnormalized Z of the data
    data_scale: float = 1.0          # robust std of the data's map
    background: list = field(default_factory=list)   # unnormalized Z of slide maxima
    background_ok: list = field(default_factory=list)  # ... passing the chi-squared test
    slide_scale: list = field(default_factory=list)  # robust std of each slide's map
    live_s: float = 0.0              # seconds of positions searched, over all slides
    inverted: np.ndarray = field(default_factory=lambda: np.zeros(0))  # unnormalized Z of
    #                                  the sign-inverted map's maxima (sidelobes left out)
    inverted_ok: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # ... passing
    #                                  the chi-squared test
    data_live_s: float = 0.0         # seconds of positions of the data's own map


def scan_maps(snr, geometry, beam_sigma, sigma_amp, live, first, cfg: SignificanceConfig,
              vetoes: Vetoes, rng) -> ScanMaps:
    """The data's map and the slides' background of one scan (``snr``: its samples), each
    background maximum flagged by ``transient_find``'s chi-squared test (``vetoes``)."""
    rows = row_offsets(geometry, beam_sigma, cfg.row_step)
    given, snr = snr, finite_snr(snr)    # once for the data's map and every slide's
    nsamp = snr.shape[1]
    window = geometry.crossing_samples(beam_sigma)
    min_shift = int(cfg.min_slide_s * geometry.sample_rate)
    slides = cfg.n_slides > 0 and nsamp > 2 * min_shift + 1
    slid = (scan_groups(live, cfg.slide_groups, nsamp, min_shift, window, rng) if slides
            else None)
    weights, norm = row_weights(geometry, rows, beam_sigma, sigma_amp, live)
    cyclic, partial = cyclic_map(snr, geometry, rows, beam_sigma, sigma_amp, live, weights,
                                 norm, slid)
    z = fill_edges(cyclic.copy(), snr, weights, norm, geometry.lag_samples)
    out = ScanMaps(first, geometry, rows, z, measured_scale(z, lags=geometry.lag_samples))
    out.inverted, out.inverted_ok = inverted_maxima(z, snr, geometry, rows, beam_sigma,
                                                    sigma_amp, live, out.data_scale, window,
                                                    cfg, vetoes)
    out.data_live_s = np.isfinite(z[0]).sum() / geometry.sample_rate
    if not slides:
        return out
    if slid is not None:
        # (in place when finite_snr copied it: nothing else reads the ungated S/N)
        snr = gated_sources(snr, partial, cyclic, geometry, weights, slid, out.data_scale,
                            window, cfg, in_place=snr is not given)
    search = SlideSearch(snr, geometry, rows, beam_sigma, sigma_amp, live, window, slid,
                         partial)
    groups = vetoes.groups(search.weights, geometry)
    floor = max(cfg.background_floor, cfg.slide_floor)
    chi2, z_norm, lags = [], [], geometry.lag_samples
    for offsets in group_offsets(slid, snr.shape[0], nsamp, min_shift, rng, cfg.n_slides):
        r, s, peak, scale = search.maxima(offsets, floor)
        out.slide_scale.append(scale)
        out.live_s += nsamp / geometry.sample_rate
        if not len(r):                       # most slides of a scan: nothing to select
            continue
        # a slide moves a bright source's (or a glitch's) detector spikes apart: each makes
        # maxima of its own that no multi-detector candidate resembles; they are left out
        keep = search.largest_share(r, s, offsets) <= cfg.max_single_share
        r, s, peak = r[keep], s[keep], peak[keep]
        chi2.extend(vetoes.chi2(snr, search.weights, geometry, lags + offsets, r, s,
                                groups=groups, cyclic=True))
        out.background.extend(peak)
        z_norm.extend(peak / scale)          # each slide in units of its own spread
    if out.background:       # the test's limits at once (their cost is per call)
        out.background_ok = list(vetoes.consistent(chi2, np.array(z_norm)))
    return out


def cyclic_map(snr, geometry, rows, beam_sigma, sigma_amp, live, weights, norm, slid):
    """``(z, partial)``: the data's map (unnormalized Z, float32 sums: Z to 1e-6, 3x faster
    than float64) summed cyclically, so that a source crossing at a scan end is on it (the
    grouped slides' gate finds it there; the data's map proper is this with the wrapped
    positions NaN), and, for slides in the groups ``slid``, the groups' partial maps whose
    sum it is (None otherwise): the slides share them, so the data's map costs only their
    sum."""
    if slid is None:
        z, _ = coherent_map(snr, geometry, rows, beam_sigma, sigma_amp, live,
                            np.zeros(snr.shape[0], np.int64), with_flux=False, finite=True,
                            dtype=np.float32)
        return z, None
    partial = partial_maps(snr, weights, geometry.lag_samples, slid)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = group_sum(partial, int(np.max(slid)) + 1) / norm.astype(np.float32)[:, None]
    return z, partial


def gated_sources(snr, partial, cyclic, geometry, weights, slid, scale, window, cfg,
                  in_place=False):
    """``snr`` with the maxima of its cyclic map ``cyclic`` (a source crossing at a scan end
    included) at least ``slide_gate`` x ``scale`` that many detectors make (real sources)
    gated out, within ``sidelobe_window`` of their passage
    (:func:`so_transients.significance.slide_groups.gate_maxima`): what grouped slides slide. The
    groups' ``partial`` maps are made those of the gated S/N (in place; ``snr`` too with
    ``in_place``)."""
    r, s = local_maxima(cyclic, cfg.slide_gate * scale, window)
    share = term_shares(snr, weights, row_members(weights), geometry.lag_samples, r, s)
    keep = share <= cfg.max_single_share
    if not keep.any():
        return snr
    half = int(round(cfg.sidelobe_window * geometry.sample_rate))
    return gate_maxima(snr, weights, geometry.lag_samples, r[keep], s[keep], half, partial,
                       slid, in_place)


def inverted_maxima(z, snr, geometry, rows, beam_sigma, sigma_amp, live, scale, window, cfg,
                    vetoes: Vetoes):
    """``(z, ok)``: unnormalized Z of the local maxima of the sign-inverted data's map ``-z``
    (noise with every correlation between detectors kept, and no source) at least
    ``background_floor`` x ``scale``, and whether each passes the chi-squared test; left
    out: those one detector makes, and a bright source's filter sidelobes (a data maximum
    ``max_opposite_ratio`` times higher within ``sidelobe_window``)."""
    r, s = local_maxima(-z, cfg.background_floor * scale, window)
    share = largest_share(snr, geometry, rows, beam_sigma, sigma_amp, live, r, s, sign=-1.0)
    half = int(round(cfg.sidelobe_window * geometry.sample_rate))
    nearby = window_max(z, r, s, 2, half)
    keep = (share <= cfg.max_single_share) & (nearby < cfg.max_opposite_ratio * -z[r, s])
    r, s = r[keep], s[keep]
    weights, _ = row_weights(geometry, rows, beam_sigma, sigma_amp, live)
    chi2 = vetoes.chi2(snr, weights, geometry, geometry.lag_samples, r, s, sign=-1.0)
    return -z[r, s], vetoes.consistent(chi2, -z[r, s] / scale)


def far_is_limit(far, far_slides, slide_hours) -> np.ndarray:
    """Whether each ``far`` is an upper limit: its ``far_slides`` is the slides' resolution,
    half a false alarm in their ``slide_hours`` (no slide maximum reached the statistic; see
    :func:`so_transients.coherent.statistic.false_alarm_rate`), and ``far`` is that value
    (the sign-inverted data give no more). Sweep stacks, ranked among their own slides'
    stacks, are not marked."""
    far, slides = np.asarray(far, float), np.asarray(far_slides, float)
    if not slide_hours > 0:
        return np.zeros(far.shape, bool)
    resolution = 0.5 / slide_hours
    with np.errstate(invalid="ignore"):
        return (np.isfinite(far) & np.isclose(slides, resolution, rtol=1e-9, atol=0)
                & (far <= slides))


def inverted_rate(statistics, inverted, live_hours, x0):
    """False alarms per hour from the sign-inverted data's maxima ``inverted`` (units of the
    statistics) over ``live_hours``: the count at least as large, or beyond ``x0`` the
    Gaussian-like tail model of :mod:`so_transients.significance.tail_model` where it is higher (NaN
    without live time)."""
    stats = np.atleast_1d(np.asarray(statistics, float))
    if not live_hours > 0:
        return np.full(stats.shape, np.nan)
    inverted = np.sort(np.asarray(inverted, float))
    counted = len(inverted) - np.searchsorted(inverted, stats, side="left")
    model = np.zeros(stats.shape)
    if x0 is not None:
        beyond = stats >= x0
        model[beyond] = np.nan_to_num(model_count_above(stats[beyond], inverted, x0))
    return np.maximum(counted, model) / live_hours


def candidate_statistic(maps: ScanMaps, bore_q, timestamps, ra, dec, t_cand, beam_sigma,
                        cfg: SignificanceConfig) -> tuple:
    """``(z, row, sample)``: the highest unnormalized Z within one row and ``peak_window``
    crossing times of the position (ra, dec) seen at ``t_cand``, and where it is on the
    map (NaN and -1 when outside the map)."""
    g = maps.geometry
    i = int(np.clip(np.searchsorted(timestamps, t_cand), 0, len(timestamps) - 1))
    row, t0, _ = map_cell(g, maps.rows, maps.first, bore_q, ra, dec, i)
    half = int(round(cfg.peak_window * beam_sigma / g.speed * g.sample_rate))
    lo, hi = max(t0 - half, 0), min(t0 + half + 1, maps.z.shape[1])
    r0 = max(row - 1, 0)
    patch = maps.z[r0:row + 2, lo:hi]
    if hi <= lo or not np.isfinite(patch).any():
        return np.nan, -1, -1
    i, j = np.unravel_index(np.nanargmax(patch), patch.shape)
    return float(patch[i, j]), r0 + int(i), lo + int(j)


@dataclass
class Background:
    """A wafer-band's noise background of the coherent statistic Z, in units of the data
    map's measured spread: the time slides' maxima over ``slide_hours`` and the sign-inverted
    data's maxima over ``data_hours`` (``scale``: the data map's spread, unnormalized), each
    flagged by whether it passes the chi-squared test."""

    slides: np.ndarray
    slide_hours: float
    inverted: np.ndarray
    data_hours: float
    slides_ok: np.ndarray | None = None    # each maximum passes the chi-squared test (None:
    inverted_ok: np.ndarray | None = None  # all do)
    scale: float = 1.0
    tail_from: float | None = 3.5    # the inverted maxima's tail model starts here
    floor: float = 3.0               # maxima were counted from this Z
    slide_floor: float | None = None  # the slides' from this one (None: ``floor``)
    stacks: np.ndarray | None = None  # Z of the inverted data's sweep stacks (None: no
    #                                   stacking), over ``data_hours``
    stack_slides: np.ndarray | None = None  # Z of the slid sweep stacks from
    stack_slide_hours: float = 0.0          # ``slide_floor``, over these hours

    def __post_init__(self):
        self.slide_floor = self.floor if self.slide_floor is None else float(self.slide_floor)
        self.slides_ok = _flags(self.slides_ok, self.slides)
        self.inverted_ok = _flags(self.inverted_ok, self.inverted)

    @classmethod
    def from_scans(cls, scans, cfg: SignificanceConfig):
        """From the :class:`ScanMaps` of a band's scans: each map in units of its own
        measured spread (the slides break the correlation of neighbouring detectors' residual
        atmosphere, so the data's Z spreads wider than theirs)."""
        scale = float(np.median([m.data_scale for m in scans])) if scans else 1.0
        slide_scales = [s for m in scans for s in m.slide_scale]
        slide_scale = float(np.median(slide_scales)) if slide_scales else 1.0
        slides = np.concatenate([np.asarray(m.background, float) for m in scans] or [[]])
        slides_ok = np.concatenate([np.asarray(m.background_ok, bool) for m in scans] or [[]])
        inverted = np.concatenate([m.inverted for m in scans] or [[]])
        inverted_ok = np.concatenate([m.inverted_ok for m in scans] or [[]]).astype(bool)
        # each map's maxima were found from the floor in its own units: in the common
        # units, those of a narrower map can fall below it, and are left out
        floor = cfg.background_floor
        slide_floor = max(floor, cfg.slide_floor)
        slides, inverted = slides / slide_scale, inverted / scale
        s, i = slides >= slide_floor, inverted >= floor
        return cls(slides[s], sum(m.live_s for m in scans) / 3600.0, inverted[i],
                   sum(m.data_live_s for m in scans) / 3600.0, slides_ok[s], inverted_ok[i],
                   scale, cfg.tail_from, floor, slide_floor)

    def far(self, z, consistent=True) -> dict:
        """``far``, ``far_slides`` and ``far_inverted`` (per hour of the wafer-band) of the
        statistics ``z`` (NaN where ``z`` is NaN; ``far_slides`` NaN below the slides' floor,
        where they were not counted); ``far`` is the higher of the two. A statistic that
        passes the chi-squared test (``consistent``, one flag or one per statistic) is
        ranked among the background maxima that pass it, one that fails among all."""
        z = np.atleast_1d(np.asarray(z, float))
        consistent = np.broadcast_to(np.asarray(consistent, bool), z.shape)
        out = {k: np.full(z.shape, np.nan) for k in ("far", "far_slides", "far_inverted")}
        for flag in (True, False):
            sel = consistent == flag
            if sel.any():
                for k, v in self._far(z[sel], flag).items():
                    out[k][sel] = v
        return out

    def _far(self, z, consistent) -> dict:
        slides = self.slides[self.slides_ok] if consistent else self.slides
        inverted = self.inverted[self.inverted_ok] if consistent else self.inverted
        slides = (false_alarm_rate(z, slides, self.slide_hours)
                  if self.slide_hours > 0 else np.full(z.shape, np.nan))
        slides = np.where(z >= self.slide_floor, slides, np.nan)
        inverted = inverted_rate(z, inverted, self.data_hours, self.tail_from)
        finite = np.isfinite(z)
        slides, inverted = np.where(finite, slides, np.nan), np.where(finite, inverted, np.nan)
        return dict(far=np.fmax(slides, inverted), far_slides=slides, far_inverted=inverted)

    def stack_far(self, z) -> dict:
        """``far``, ``far_slides`` and ``far_inverted`` (per hour of the wafer-band) of sweep
        stacks with statistics ``z``, as :meth:`far` for single crossings: the slid stacks
        at least as high (:mod:`so_transients.significance.stack_slides`; NaN below the slides' floor or
        without them) and the inverted data's stacks, counted and beyond ``tail_from``
        modelled; ``far`` is the higher (all NaN without stacking)."""
        z = np.atleast_1d(np.asarray(z, float))
        out = {k: np.full(z.shape, np.nan) for k in ("far", "far_slides", "far_inverted")}
        if self.stacks is None:
            return out
        finite = np.isfinite(z)
        out["far_inverted"] = np.where(finite, inverted_rate(z, self.stacks, self.data_hours,
                                                             self.tail_from), np.nan)
        if self.stack_slides is not None and self.stack_slide_hours > 0:
            slides = false_alarm_rate(z, self.stack_slides, self.stack_slide_hours)
            out["far_slides"] = np.where(finite & (z >= self.slide_floor), slides, np.nan)
        out["far"] = np.fmax(out["far_slides"], out["far_inverted"])
        return out

    def threshold(self, rate, step=0.005, top=30.0, stacked=False, consistent=True) -> float:
        """The lowest Z (to ``step``) whose ``far`` (``stacked``: a sweep stack's;
        ``consistent``: of a maximum passing the chi-squared test) is at most ``rate`` (NaN
        when no Z up to ``top`` reaches it, e.g. slides too short to resolve it)."""
        grid = np.arange(self.floor, top, step)
        far = (self.stack_far if stacked else lambda z: self.far(z, consistent))(grid)["far"]
        ok = np.flatnonzero(far <= rate)
        return float(grid[ok[0]]) if len(ok) else np.nan


def _flags(flags, values):
    """Per-maximum flags, all True when None."""
    return np.ones(len(values), bool) if flags is None else np.asarray(flags, bool)


def band_background(snr, dets, timestamps, bore_q, xi, eta, scan, sigma_amp, beam_sigma,
                    sample_rate, cfg: SignificanceConfig, vetoes: Vetoes, visit=None,
                    stacking: StackSettings | None = None):
    """``(background, maps)``: the :class:`Background` of one band of a group and, with
    ``stacking`` (``transient_find``'s sweep stacking), every scan's data map as stacking
    reads it (:func:`stack_map`; empty without), the background's ``stacks`` being the
    sign-inverted maps' stacks, seeded and selected as the data's. ``dets``: the rows of
    ``snr`` (the group's S/N, possibly memory-mapped: one scan of these rows is read at a
    time) of the band's live detectors; ``xi``, ``eta``, ``sigma_amp``: theirs.
    ``vetoes``: ``transient_find``'s glitch vetoes, which select the background as they
    select its candidates. ``visit(scan, maps, snr)`` is called with each scan's
    :class:`ScanMaps` and S/N while its data map is held."""
    live = np.ones(len(dets), bool)
    rng = np.random.default_rng(cfg.seed)
    scans, stack_maps, seeds, data_seeds = [], [], [], []
    for s in np.unique(scan[scan >= 0]):
        samples = np.flatnonzero(scan == s)
        geometry = crossing_geometry(timestamps, bore_q, xi, eta, samples, sample_rate)
        block = np.asarray(snr[dets, samples[0]:samples[-1] + 1])
        maps = scan_maps(block, geometry, beam_sigma, sigma_amp, live, samples[0], cfg,
                         vetoes, rng)
        if visit is not None:
            visit(s, maps, block)
        if stacking is not None:
            stack_maps.append(stack_map(s, maps, beam_sigma, sigma_amp, live, timestamps))
            for sign, found in ((-1.0, seeds), (1.0, data_seeds)):
                found += map_seeds(block, stack_maps[-1], beam_sigma, sigma_amp, live, bore_q,
                                   cfg.row_step, stacking, vetoes, sign)
        maps.z = None                        # only the background is kept
        scans.append(maps)
    background = Background.from_scans(scans, cfg)
    if stacking is not None:
        background.stacks = inverted_stacks(stack_maps, seeds, bore_q, timestamps, beam_sigma,
                                            cfg.row_step, stacking, cfg.background_floor)
        min_shift = int(cfg.min_slide_s * sample_rate)
        background.stack_slides = slid_stacks(stack_maps, data_seeds, bore_q, timestamps,
                                              beam_sigma, cfg.row_step, stacking,
                                              background.slide_floor, cfg.n_slides, min_shift,
                                              rng)
        background.stack_slide_hours = cfg.n_slides * background.data_hours
    return background, stack_maps


def group_significance(snr, dets, timestamps, bore_q, xi, eta, scan, sigma_amp, beam_sigma,
                       sample_rate, cands, cfg: SignificanceConfig, vetoes: Vetoes,
                       stacking: StackSettings | None = None) -> dict:
    """``coherent_snr``, ``coherent_chi2``, ``coherent_consistent``, ``far``, ``far_slides``,
    ``far_inverted`` and ``pass_far`` of every
    candidate of one band of a group (``cands``: ``ra``, ``dec``, ``t_median``, ``scan``,
    and for sweep stacks ``n_crossings``, ``t_start``, ``t_stop``), and the group's
    background ``live_hours`` and ``z_scale`` (arguments as :func:`band_background`).
    ``stacking``: ``transient_find``'s sweep stacking, which its stacks' statistic and
    background repeat (:func:`stack_significance`)."""
    n = len(cands["scan"])
    stat, chi2 = np.full(n, np.nan), np.full(n, np.nan)
    stacked = np.asarray(cands.get("n_crossings", np.ones(n, int))) > 1
    stacking = stacking if stacked.any() else None
    live = np.ones(len(dets), bool)

    def visit(s, scan_maps, block):
        g = scan_maps.geometry
        weights, _ = row_weights(g, scan_maps.rows, beam_sigma, sigma_amp, live)
        for c in np.flatnonzero((np.asarray(cands["scan"]) == s) & ~stacked):
            stat[c], row, sample = candidate_statistic(
                scan_maps, bore_q, timestamps, cands["ra"][c], cands["dec"][c],
                cands["t_median"][c], beam_sigma, cfg)
            if row >= 0:
                chi2[c] = vetoes.chi2(block, weights, g, g.lag_samples, [row], [sample])[0]

    background, maps = band_background(snr, dets, timestamps, bore_q, xi, eta, scan,
                                       sigma_amp, beam_sigma, sample_rate, cfg, vetoes, visit,
                                       stacking)
    z = stat / background.scale
    consistent = vetoes.consistent(chi2, z)
    out = background.far(z, consistent)
    out["coherent_snr"], out["coherent_chi2"], out["coherent_consistent"] = z, chi2, consistent
    if stacking is not None:
        for key, values in stack_significance(maps, cands, stacked, bore_q, beam_sigma,
                                              background, cfg).items():
            out[key][stacked] = values
    # a candidate without a far (no slides possible, or its crossing reaches a scan end)
    # is not cut
    out["pass_far"] = np.ones(n, bool) if cfg.max_far is None else ~(out["far"] > cfg.max_far)
    return dict(**out, live_hours=background.slide_hours, z_scale=background.scale)


def stack_map(s, maps: ScanMaps, beam_sigma, sigma_amp, live, timestamps) -> ScanMap:
    """A scan's data map as sweep stacking reads it, in units of its own measured spread
    (as ``transient_find``'s stacks are)."""
    _, norm = row_weights(maps.geometry, maps.rows, beam_sigma, sigma_amp, live)
    with np.errstate(invalid="ignore", divide="ignore"):
        flux = maps.z / norm[:, None]
    last = maps.first + maps.z.shape[1] - 1
    return ScanMap(int(s), maps.first, maps.geometry, maps.rows,
                   (maps.z / maps.data_scale).astype(np.float32), flux.astype(np.float32),
                   norm / maps.data_scale, float(timestamps[maps.first]),
                   float(timestamps[last]))


def stack_significance(maps, cands, stacked, bore_q, beam_sigma, background: Background,
                       cfg) -> dict:
    """``coherent_snr``, ``far``, ``far_slides`` and ``far_inverted`` of the sweep stacks
    among ``cands`` (``stacked``): the stacked Z over the crossings between their
    ``t_start`` and ``t_stop``, and :meth:`Background.stack_far`, the slid and the
    sign-inverted maps' stacks at least as high."""
    reach = cfg.row_step * beam_sigma
    z = []
    for c in np.flatnonzero(stacked):
        res = stack_at(maps, bore_q, cands["ra"][c], cands["dec"][c],
                       cands["t_start"][c] - 1.0, cands["t_stop"][c] + 1.0, reach)
        z.append(np.nan if res is None else res["z"])
    z = np.asarray(z, float)
    return dict(coherent_snr=z, **background.stack_far(z))


def significance_by_band(snr, timestamps, bore_q, xi, eta, scan, sigma_amp, live, beam_sigma,
                         bands, cands, cfg: SignificanceConfig, vetoes: Vetoes,
                         stacking=None):
    """``(columns, live_hours, z_scale)``: :func:`group_significance` for each band of a
    group (its detectors and candidates), the ``transient_significance`` columns for every
    candidate (candidates of a band with no live detector: NaN, passing), and the background
    live time and Z scale of the group (the first band's; one band per group in SO's
    grouping). ``stacking``: ``transient_find``'s sweep stacking (:class:`StackSettings`)
    or None."""
    n = len(cands["scan"])
    out = dict(coherent_snr=np.full(n, np.nan), coherent_chi2=np.full(n, np.nan),
               coherent_consistent=np.ones(n, bool), far=np.full(n, np.nan),
               far_slides=np.full(n, np.nan), far_inverted=np.full(n, np.nan),
               pass_far=np.ones(n, bool))
    fs = rate_of(timestamps)
    live_hours, scale = np.nan, np.nan
    for band in np.unique(bands):
        dets = np.flatnonzero((bands == band) & live)
        sel = np.flatnonzero(np.asarray(cands["bandpass"]) == band)
        if not len(dets):
            continue
        sub = dict(ra=np.asarray(cands["cluster_ra"])[sel],
                   dec=np.asarray(cands["cluster_dec"])[sel],
                   t_median=np.asarray(cands["t_median"])[sel],
                   scan=np.asarray(cands["scan"])[sel])
        for key in ("n_crossings", "t_start", "t_stop"):
            if key in cands:
                sub[key] = np.asarray(cands[key])[sel]
        res = group_significance(snr, dets, timestamps, bore_q, xi[dets], eta[dets], scan,
                                 sigma_amp[dets], float(np.median(beam_sigma[dets])), fs, sub,
                                 cfg, vetoes, stacking)
        for k in out:
            out[k][sel] = res[k]
        if not np.isfinite(live_hours):
            live_hours, scale = res["live_hours"], res["z_scale"]
    return out, float(live_hours), float(scale)
