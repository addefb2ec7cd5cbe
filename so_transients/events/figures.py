"""One figure per event: its light curve per band with the eq. 1 fit and the detections
marked, and its position with the error circle over the detector tracks of its best
crossings."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from so_transients.common.angles import ARCSEC, tangent_offsets  # noqa: E402
from so_transients.common.flare_model import flare_flux  # noqa: E402

BAND_COLORS = {"f090": "tab:blue", "f150": "tab:orange", "f220": "tab:green",
               "f280": "tab:red"}


#: Least half-width of the light curve's time axis (s): an event seen at one crossing is
#: still drawn on a readable axis.
MIN_HALF_SPAN_S = 30.0


def time_limits(t) -> tuple:
    """The light curve's time axis (s): every point, padded by 5 % of their span, and at
    least ``MIN_HALF_SPAN_S`` either side of their middle."""
    t = np.asarray(t, float)
    t = t[np.isfinite(t)]
    if not len(t):
        return -MIN_HALF_SPAN_S, MIN_HALF_SPAN_S
    lo, hi = float(t.min()), float(t.max())
    pad = 0.05 * (hi - lo)
    mid, half = 0.5 * (lo + hi), max(0.5 * (hi - lo) + pad, MIN_HALF_SPAN_S)
    return mid - half, mid + half


def _light_curve(ax, lc, fits, t0, t0_utc):
    for band in np.unique(lc["bandpass"]) if len(lc) else []:
        mine = lc[lc["bandpass"] == band]
        color = BAND_COLORS.get(band, "k")
        t = mine["ctime"] - t0
        limit = np.isfinite(mine["upper_limit"])
        ax.errorbar(t[~limit], mine["flux"][~limit], mine["flux_err"][~limit], fmt="o",
                    color=color, ms=4, label=band)
        ax.plot(t[limit], mine["upper_limit"][limit], "v", color=color, alpha=0.5, ms=5)
        det = np.asarray(mine["detected"], bool)
        ax.plot(t[det], mine["flux"][det], "*", color=color, mec="k", ms=12)
        fit = fits[fits["bandpass"] == band]
        if len(fit) and fit["fit_ok"][0]:
            f = fit[0]
            grid = np.linspace(t.min(), t.max(), 800) + t0
            ax.plot(grid - t0, flare_flux(grid, f["t_peak"], f["s_peak"], f["t_rise"],
                                          f["t_decay"], f["eta_rise"], f["eta_decay"]),
                    color=color, lw=1)
    ax.axhline(0, color="0.7", lw=0.5)
    ax.set_xlim(*time_limits(np.asarray(lc["ctime"], float) - t0 if len(lc) else []))
    ax.set_xlabel(f"time - {t0_utc} UTC (first detection) [s]")
    ax.set_ylabel("flux density [mJy]")
    ax.legend(fontsize=8, title="* detected, v upper limit", title_fontsize=7)


def _position(ax, event, detections, tracks):
    """Offsets in arcsec from the event's position: the detector tracks (grey), each
    detection with its errors, the event's 1 sigma circle; the box spans a few errors."""
    ra0, dec0 = np.radians(event["ra"]), np.radians(event["dec"])
    det_off = tangent_offsets(np.asarray(detections["ra"], float),
                              np.asarray(detections["dec"], float), ra0, dec0) / ARCSEC
    half = max(60.0, 10 * float(event["pos_err"]), 1.5 * float(np.max(np.abs(det_off),
                                                                       initial=0.0)))
    for track in tracks:
        off = tangent_offsets(track[0].ravel(), track[1].ravel(), ra0, dec0) / ARCSEC
        for line in off.reshape(track.shape[1], track.shape[2], 2):
            ax.plot(line[:, 0], line[:, 1], color="0.85", lw=0.6, zorder=0)
    ax.errorbar(det_off[:, 0], det_off[:, 1],
                xerr=np.asarray(detections["ra_err"], float) / ARCSEC,
                yerr=np.asarray(detections["dec_err"], float) / ARCSEC, fmt=".", color="k",
                label="detections")
    ax.add_patch(plt.Circle((0, 0), float(event["pos_err"]), fill=False, color="r",
                            label=f"event, 1 sigma {event['pos_err']:.1f}\""))
    ax.set_xlim(half, -half)          # RA grows to the east (left)
    ax.set_ylim(-half, half)
    ax.set_aspect("equal")
    ax.set_xlabel("RA offset [arcsec]")
    ax.set_ylabel("Dec offset [arcsec]")
    ax.set_title("detector tracks of the best crossings", fontsize=9)
    ax.legend(fontsize=8, loc="upper right")


def plot_event(event, lc, fits, detections, tracks, path):
    """Write the figure of ``event`` (an events row) to ``path``."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5),
                                      gridspec_kw={"width_ratios": [2, 1]})
    _light_curve(left, lc, fits, float(event["t_first"]), event["t_first_utc"])
    _position(right, event, detections, tracks)
    fig.suptitle(f"event {event['event_id']}: {event['name']}  ({event['bands']}; "
                 f"{event['n_detections']} detections, {event['n_crossings']} crossings)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
