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


def _title(aman, cand):
    cands = aman.transient_candidates
    obs_id = aman.obs_info.obs_id if "obs_info" in aman else ""
    utc = Time(float(cands.t_peak[cand]), format="unix").utc.isot[:22]
    return (f"{obs_id} {detection_name(aman, cand)}   {utc} UTC\n"
            f"flux {cands.flux[cand]:.0f} ± {cands.flux_err[cand]:.0f} mJy, fitted S/N "
            f"{cands.snr_fit[cand]:.1f}, RA {np.degrees(cands.ra[cand]):.4f}°, "
            f"Dec {np.degrees(cands.dec[cand]):.4f}°")


def _model(aman, cand, dets, lo, hi):
    """The fitted beam model (mJy) of detectors ``dets`` over samples ``lo:hi``."""
    cands = aman.transient_candidates
    data = FitInputs.from_aman(aman)
    _, track = source_track(data, float(cands.ra[cand]), float(cands.dec[cand]), lo, hi, dets)
    track.sigma = float(np.median(data.beam_sigma[dets]))
    shape = beam_shape(track, data.xi[dets], data.eta[dets])
    return cands.flux[cand] * shape + cands.offset[cand], data


def plot_detection(aman, cand, filename, window=1.0, max_lines=8):
    """The contributing detectors' amplitude (mJy) around a detection with the fitted beam
    model over them, and where they are on the focal plane.

    ``aman`` needs the transient steps' outputs (``transient_snr``, ``transient_filter``,
    ``transient_candidates``, ``transient_hits``) and the standard pointing fields. Writes
    ``filename`` (PNG) and returns it.
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
    fig, (ax_t, ax_fp) = plt.subplots(1, 2, figsize=(12, 4.8),
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
    ax_fp.scatter(xi, eta, s=4, color="0.85")
    sc = ax_fp.scatter(xi[dets], eta[dets], c=peak_snr, s=18, cmap="viridis")
    fig.colorbar(sc, ax=ax_fp, label="peak S/N")
    ax_fp.set(xlabel="xi (deg)", ylabel="eta (deg)", aspect="equal",
              title=f"{len(dets)} detectors above the S/N threshold")
    fig.suptitle(_title(aman, cand), fontsize=9)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(filename)), exist_ok=True)
    fig.savefig(filename, dpi=90)
    plt.close(fig)
    return filename
