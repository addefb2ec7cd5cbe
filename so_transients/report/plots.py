"""The vetting page's figures of one event: its sky cutouts and its detectors' time streams.

* :func:`plot_cutouts`: per band, the cutout made from the TOD (the binned filtered signal,
  ``cutouts/*.fits``) in arcminutes from the event's position, with the fitted position and
  its error circle, each detection's position, the catalogue match, and the beam FWHM;
* :func:`plot_streams`: per band, the detectors closest to the source's path around the best
  crossing: the preprocessed signal, the filtered signal with the beam fit's model over it,
  and the residual (filtered - model).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from astropy.io import fits  # noqa: E402
from astropy.table import Table  # noqa: E402
from astropy.wcs import WCS  # noqa: E402

from so_transients.common.angles import ARCMIN, tangent_offsets  # noqa: E402
from so_transients.common.times import utc  # noqa: E402


def _offsets_arcmin(ra_deg, dec_deg, ra0_deg, dec0_deg):
    off = tangent_offsets(np.radians(np.atleast_1d(ra_deg)), np.radians(np.atleast_1d(dec_deg)),
                          np.radians(ra0_deg), np.radians(dec0_deg))
    return off / ARCMIN


def _pixel_offsets(path, event):
    """The cutout's map and its pixel centres' offsets (arcmin, east and north) from the
    event's position."""
    with fits.open(path) as hdus:
        sky, wcs = hdus[0].data.astype(float), WCS(hdus[0].header)
    ny, nx = sky.shape
    iy, ix = np.mgrid[:ny, :nx]
    ra, dec = wcs.all_pix2world(ix.ravel(), iy.ravel(), 0)
    off = _offsets_arcmin(ra, dec, event["ra"], event["dec"])
    return sky, off[:, 0].reshape(ny, nx), off[:, 1].reshape(ny, nx)


def plot_cutouts(event: dict, cutouts, detections, folder, path):
    """One panel per row of ``cutouts`` (the event's rows of cutouts.ecsv; files relative to
    ``folder``) for ``event`` (its events row as a dict); written to ``path``."""
    n = max(len(cutouts), 1)
    fig, axes = plt.subplots(1, n, figsize=(4.6 * n, 4.2), squeeze=False)
    for ax, row in zip(axes[0], cutouts):
        sky, east, north = _pixel_offsets(folder / row["file"], event)
        lim = float(np.nanmax(np.abs(sky))) if np.isfinite(sky).any() else 1.0
        extent = (east[0, 0], east[0, -1], north[0, 0], north[-1, 0])   # pixel centres
        step_x = (extent[1] - extent[0]) / max(sky.shape[1] - 1, 1) / 2
        step_y = (extent[3] - extent[2]) / max(sky.shape[0] - 1, 1) / 2
        mesh = ax.imshow(sky, origin="lower", cmap="RdBu_r", vmin=-lim, vmax=lim,
                         extent=(extent[0] - step_x, extent[1] + step_x, extent[2] - step_y,
                                 extent[3] + step_y), interpolation="nearest")
        fig.colorbar(mesh, ax=ax, label="filtered amplitude [mJy]", shrink=0.85)
        err = float(event["pos_err"]) / 60.0
        ax.plot(0, 0, "+", color="k", ms=14, mew=1.5, label="fitted position")
        ax.add_patch(plt.Circle((0, 0), max(err, 0.02), fill=False, color="k", lw=1))
        fwhm = float(row["beam_fwhm"])
        if np.isfinite(fwhm):
            ax.add_patch(plt.Circle((0, 0), fwhm / 2, fill=False, color="0.3", ls=":",
                                    label=f"beam FWHM {fwhm:.1f}'"))
        mine = detections[np.asarray(detections["bandpass"]).astype(str) == str(row["bandpass"])]
        if len(mine):
            off = _offsets_arcmin(np.degrees(np.asarray(mine["ra"], float)),
                                  np.degrees(np.asarray(mine["dec"], float)),
                                  event["ra"], event["dec"])
            ax.plot(off[:, 0], off[:, 1], "x", color="tab:green", ms=7, label="detections")
        if np.isfinite(float(event.get("cat_ra", np.nan))):
            off = _offsets_arcmin(event["cat_ra"], event["cat_dec"], event["ra"], event["dec"])
            ax.plot(off[:, 0], off[:, 1], "o", mfc="none", mec="tab:purple", ms=12, mew=1.5,
                    label=f"catalogue: {event['cat_source_name']}")
        half = float(np.nanmax(np.abs(east)))
        ax.set_xlim(half, -half)          # east to the left
        ax.set_ylim(-half, half)
        ax.set_aspect("equal")
        ax.set_xlabel("RA offset [arcmin]")
        ax.set_ylabel("Dec offset [arcmin]")
        ax.set_title(f"{row['bandpass']}  {row['obs_id']} {row['wafer_slot']}\n"
                     f"{row['time']} UTC, S/N {row['snr']:.1f}", fontsize=9)
        ax.legend(fontsize=7, loc="lower left")
    fig.subplots_adjust(left=0.08, right=0.95, bottom=0.13, top=0.86, wspace=0.35)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _stacked(ax, t, traces, step, color, lw=0.7, **kw):
    """Traces one above the other, ``step`` apart (the first on top)."""
    for r, trace in enumerate(traces):
        ax.plot(t, trace - r * step, color=color, lw=lw, **kw if r == 0 else {})


def plot_streams(cutouts, folder, path):
    """Per band and crossing (a row each), the detectors' time streams one above the other:
    the preprocessed signal, the filtered signal with the beam fit's model, and the residual
    (filtered - model); written to ``path``."""
    from so_transients.events.cutouts import crossings_of

    rows = [(row, c) for row in cutouts
            for c in crossings_of(dict(np.load(folder / row["streams"])))]
    n_rows = max(len(rows), 1)
    height = 3.0 * n_rows + 0.6
    fig, axes = plt.subplots(n_rows, 3, figsize=(13, height), squeeze=False)
    for (raw_ax, filt_ax, res_ax), (row, s) in zip(axes, rows):
        when = str(utc(float(s["ctime"]))[0])
        if not len(s["dets"]):
            raw_ax.set_title(f"{row['bandpass']} {when}: no detector near the source",
                             fontsize=9)
            continue
        filtered, model = s["filtered"], s["model"]
        step = 1.2 * float(np.nanmax(np.abs(filtered), initial=1.0))
        raw_step = 1.2 * float(np.nanmax(np.abs(s["raw"]), initial=0.0)) or step
        _stacked(raw_ax, s["t"], s["raw"], raw_step, "0.35")
        _stacked(filt_ax, s["t"], filtered, step, "k", label="filtered")
        _stacked(filt_ax, s["t"], model, step, "tab:red", lw=1.0, label="beam fit")
        _stacked(res_ax, s["t"], filtered - model, step, "tab:blue")
        for ax, st in ((raw_ax, raw_step), (filt_ax, step), (res_ax, step)):
            ax.set_yticks(-st * np.arange(len(s["dets"])))
            ax.set_yticklabels([f"{name}\n{a:.1f} sigma" for name, a in
                                zip(s["det_names"], s["across"])] if ax is raw_ax else [],
                               fontsize=6)
            ax.set_xlabel(f"time - {when} UTC [s]", fontsize=8)
            ax.tick_params(labelsize=7)
        raw_ax.set_title(f"{row['bandpass']}, forced S/N {float(s['snr']):.1f}: preprocessed",
                         fontsize=9)
        filt_ax.set_title(f"filtered [mJy, {step:.0f} apart] and beam fit", fontsize=9)
        res_ax.set_title("residual: filtered - fit", fontsize=9)
        filt_ax.legend(fontsize=7, loc="upper right")
    fig.subplots_adjust(left=0.13, right=0.98, bottom=0.6 / height, top=1 - 0.3 / height,
                        wspace=0.08, hspace=0.45)
    fig.savefig(path, dpi=80)
    plt.close(fig)


@dataclass
class FigureJob:
    """One event's figures: picklable, for a process pool or an MPI rank."""

    event: dict              # its events row
    cutouts: Table           # its rows of cutouts.ecsv
    detections: Table        # its detections (bandpass, ra, dec)
    folder: Path             # the events folder (the cutouts' and streams' files)
    cutout_png: Path
    streams_png: Path


def draw_event_figures(job: FigureJob) -> str:
    """Both figures of one event (:func:`plot_cutouts`, :func:`plot_streams`)."""
    plot_cutouts(job.event, job.cutouts, job.detections, job.folder, job.cutout_png)
    plot_streams(job.cutouts, job.folder, job.streams_png)
    return str(job.cutout_png)
