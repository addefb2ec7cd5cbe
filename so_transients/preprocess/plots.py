"""Figures a person would rather look at than read: one per detection."""
from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from astropy.time import Time  # noqa: E402

from so_transients.detect.fit import FitInputs, beam_shape, source_track  # noqa: E402


def detection_name(aman, cand) -> str:
    """``<wafer>_<band>_cand<id>``: how plot files and printed lists name a candidate."""
    cands = aman.transient_candidates
    return f"{cands.wafer_slot[cand] or 'wafer'}_{cands.bandpass[cand]}_cand{int(cands.cand_id[cand])}"


def detection_filename(template, aman, cand, step) -> str:
    """The PNG of detection ``cand``: in the folder of sotodlib's ``template``
    (``<plot_dir>/{ctime}/{obsid}/<step index>_{name}.png``, ``{ctime}`` its first 5 digits),
    named ``<step>_<wafer>_<band>_cand<id>.png`` by the step rather than by its index in
    ``process_pipe``, which moves when a step is inserted before it."""
    folder = os.path.dirname(template).replace("{ctime}", str(aman.timestamps[0])[:5])
    folder = folder.replace("{obsid}", aman.obs_info.obs_id if "obs_info" in aman else "obs")
    return os.path.join(folder, f"{step}_{detection_name(aman, cand)}.png")


def _value(cands, name, cand) -> float:
    """Column ``name`` of candidate ``cand``; NaN when the step filling it did not run."""
    return float(cands[name][cand]) if name in cands._fields else np.nan


def find_mode(aman, cand) -> str:
    """``"coherent"`` or ``"paper"``: the ``transient_find`` mode that found ``cand``, from
    what that step stored (``map_z``: the coherent statistic, NaN in paper mode)."""
    return "paper" if np.isnan(_value(aman.transient_candidates, "map_z", cand)) else "coherent"


def statistics_line(aman, cand) -> str:
    """Which mode found ``cand``, its ``map_z`` and its ``far`` (false alarms per
    wafer-band-hour), each saying why it is missing when it is."""
    cands = aman.transient_candidates
    mode = find_mode(aman, cand)
    z = _value(cands, "map_z", cand)
    far = _value(cands, "far", cand)
    z_text = "map_z n/a (paper mode)" if np.isnan(z) else f"map_z {z:.2f}"
    if "far" not in cands._fields:
        far_text = "far n/a (no transient_significance)"
    elif np.isnan(far):
        far_text = "far n/a (not computed)"
    else:
        far_text = f"far {far:.3g} per wafer-band-hour"
    return f"found by transient_find mode: {mode}; {z_text}; {far_text}"


def _title(aman, cand):
    cands = aman.transient_candidates
    obs_id = aman.obs_info.obs_id if "obs_info" in aman else ""
    utc = Time(float(cands.t_peak[cand]), format="unix").utc.isot[:22]
    return (f"{obs_id} {detection_name(aman, cand)}   {utc} UTC\n"
            f"flux {cands.flux[cand]:.0f} ± {cands.flux_err[cand]:.0f} mJy, fitted S/N "
            f"{cands.snr_fit[cand]:.1f}, RA {np.degrees(cands.ra[cand]):.4f}°, "
            f"Dec {np.degrees(cands.dec[cand]):.4f}°\n{statistics_line(aman, cand)}")


#: What ``transient_hits`` holds in each mode: (focal-plane title, colour-bar label).
HIT_LABELS = {
    "paper": ("{n} detectors with clustered samples\nat or above the S/N threshold",
              "peak S/N of the clustered samples"),
    "coherent": ("{n} detectors in the coherent sum\nnear the peak, of either sign",
                 "S/N where the position crosses the detector"),
}


def _model(aman, cand, dets, lo, hi):
    """The fitted beam model (mJy) of detectors ``dets`` over samples ``lo:hi``."""
    cands = aman.transient_candidates
    data = FitInputs.from_aman(aman)
    _, track = source_track(data, float(cands.ra[cand]), float(cands.dec[cand]), lo, hi, dets)
    track.sigma = float(np.median(data.beam_sigma[dets]))
    shape = beam_shape(track, data.xi[dets], data.eta[dets])
    return cands.flux[cand] * shape + cands.offset[cand], data


def detection_figure(aman, cand, window=1.0, max_lines=8):
    """The figure :func:`plot_detection` saves, returned open (close it with
    ``plt.close(fig)``).

    The contributing detectors are those of ``transient_hits``: in paper mode the
    detectors of the candidate's cluster of samples at or above the S/N threshold, coloured
    by their highest S/N; in coherent mode the detectors whose terms of the coherent sum lie
    near the peak, whatever their sign, coloured by their S/N where the position crosses them.
    """
    cands, hits = aman.transient_candidates, aman.transient_hits
    mine = np.asarray(hits.cand).astype(int) == cand
    dets = np.unique(np.asarray(hits.det)[mine].astype(int))
    peak_snr = np.array([np.asarray(hits.snr)[mine][np.asarray(hits.det)[mine] == d].max()
                         for d in dets])
    order = dets[np.argsort(-peak_snr)][:max_lines]
    t = np.asarray(aman.timestamps)
    t0 = float(cands.t_peak[cand])
    lo, hi = np.searchsorted(t, [t0 - window, t0 + window])
    model, data = _model(aman, cand, order, lo, hi)
    amp = data.amplitude(order, lo, hi)
    fig, (ax_t, ax_fp) = plt.subplots(1, 2, figsize=(12, 5.0),
                                      gridspec_kw={"width_ratios": [1.6, 1]})
    step = 1.5 * max(float(np.max(model)), 1.0)
    for k, d in enumerate(order):
        ax_t.plot(t[lo:hi] - t0, amp[k] + k * step, lw=0.7, color="0.4")
        ax_t.plot(t[lo:hi] - t0, model[k] + k * step, lw=1.2, color="C3")
        ax_t.text(-window, k * step, str(aman.dets.vals[d]), fontsize=6, va="bottom")
    ax_t.plot([], [], color="0.4", label="data (amplitude)")
    ax_t.plot([], [], color="C3", label="fitted beam model")
    ax_t.set(xlabel=f"time - t_peak (s); t_peak = {t0:.2f} (ctime)",
             ylabel=f"amplitude (mJy), detectors offset by {step:.0f}")
    ax_t.legend(fontsize=7, loc="upper right")
    xi, eta = np.degrees(data.xi), np.degrees(data.eta)
    title, colour = HIT_LABELS[find_mode(aman, cand)]
    ax_fp.scatter(xi, eta, s=4, color="0.85")
    sc = ax_fp.scatter(xi[dets], eta[dets], c=peak_snr, s=18, cmap="viridis")
    fig.colorbar(sc, ax=ax_fp, label=colour)
    ax_fp.set_title(title.format(n=len(dets)), fontsize=9)
    ax_fp.set(xlabel="xi (deg)", ylabel="eta (deg)", aspect="equal")
    fig.suptitle(_title(aman, cand), fontsize=9)
    fig.tight_layout()
    return fig


def plot_detection(aman, cand, filename, window=1.0, max_lines=8):
    """The contributing detectors' amplitude (mJy) around a detection with the fitted beam
    model over them, and where they are on the focal plane (:func:`detection_figure`); the
    title says which ``transient_find`` mode found it, with its ``map_z`` and ``far``.

    ``aman`` needs the transient steps' outputs (``transient_snr``, ``transient_filter``,
    ``transient_candidates``, ``transient_hits``) and the standard pointing fields. Writes
    ``filename`` (PNG) and returns it.
    """
    fig = detection_figure(aman, cand, window, max_lines)
    os.makedirs(os.path.dirname(os.path.abspath(filename)), exist_ok=True)
    fig.savefig(filename, dpi=90)
    plt.close(fig)
    return filename
