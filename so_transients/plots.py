"""Figures a person would rather look at than read: one per detection."""
from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def plot_detection(aman, cand, filename, window=1.0, max_lines=12):
    """S/N of a candidate's detectors around the event, and their place on the focal plane.

    ``aman`` needs ``transient_snr``, ``transient_candidates`` and ``transient_hits`` (from the
    transient steps) and ``focal_plane``. Writes ``filename`` (PNG) and returns it.
    """
    cands, hits = aman.transient_candidates, aman.transient_hits
    mine = np.asarray(hits.cand).astype(int) == cand
    dets = np.unique(np.asarray(hits.det)[mine].astype(int))
    peak_snr = np.array([np.asarray(hits.snr)[mine][np.asarray(hits.det)[mine] == d].max()
                         for d in dets])
    order = dets[np.argsort(-peak_snr)][:max_lines]
    t = np.asarray(aman.timestamps)
    t0 = float(cands.t_peak[cand])
    sel = np.abs(t - t0) < window
    fig, (ax_t, ax_fp) = plt.subplots(1, 2, figsize=(11, 4.2),
                                      gridspec_kw={"width_ratios": [1.6, 1]})
    for d in order:
        ax_t.plot(t[sel] - t0, aman.transient_snr[d, sel], lw=0.8, label=str(aman.dets.vals[d]))
    ax_t.axhline(3, color="gray", ls=":", lw=0.8)
    ax_t.set(xlabel=f"time - {t0:.2f} (s, ctime)", ylabel="matched-filter S/N",
             title=f"{aman.obs_info.obs_id if 'obs_info' in aman else ''} candidate {cand}")
    ax_t.legend(fontsize=6, ncol=2, loc="upper right")
    xi = np.degrees(np.asarray(aman.focal_plane.xi))
    eta = np.degrees(np.asarray(aman.focal_plane.eta))
    ax_fp.scatter(xi, eta, s=4, color="0.85")
    sc = ax_fp.scatter(xi[dets], eta[dets], c=peak_snr, s=18, cmap="viridis")
    fig.colorbar(sc, ax=ax_fp, label="peak S/N")
    flux = cands.flux[cand] if "flux" in cands._fields else np.nan
    ax_fp.set(xlabel="xi (deg)", ylabel="eta (deg)", aspect="equal",
              title=f"{cands.bandpass[cand]}: {flux:.0f} mJy, {len(dets)} detectors")
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(filename)), exist_ok=True)
    fig.savefig(filename, dpi=90)
    plt.close(fig)
    return filename
