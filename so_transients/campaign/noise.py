"""The campaign's noise-only observations: simulated once, preprocessed and filtered once.

Each group (observation x wafer x band) is simulated on its own, into
``<output>/noise/sim/<group>/`` (:func:`simulate_group`; its data are those of the whole
simulation), so that a campaign can simulate one group while it preprocesses another.
For every group the site config's steps up to
``transient_filter`` run through sotodlib's ``Pipeline`` on the noise-only TOD. What injections
need is then kept on disk, under ``<output>/noise/groups/<group>/``:

* ``snr.npy``: the noise-only S/N timestream (float32, dets x samps), opened memory-mapped so
  each worker reads only the windows it needs;
* ``state.h5``: the rest of the AxisManager without the signal (timestamps, boresight and its
  quaternions, focal plane, det_info, flags, ``transient_filter`` with the noise model);
* ``info.json``: the fit's error scale measured on the noise, the duration and noise level,
  and whether the standard steps deconvolve detector time constants;
* ``detectors.npz``: when the simulation gave the detectors imperfections, each detector's
  true focal-plane position, sky response (gain) and time constant, from the simulation's
  truth, so that injected flares are seen as the TOD's sources are (:class:`Response`);
* ``false_noise.ecsv`` / ``false_inverted.ecsv`` and ``false_positives.json`` (their counts):
  the detections of the search steps run on the noise-only S/N and on its sign-inverted copy;
  ``fitted_noise.ecsv`` / ``fitted_inverted.ecsv``: every candidate fitted there, at any
  fitted S/N (the false-detection rate as a function of a raised threshold)
  (the site pipeline on -TOD: every standard step and the filter are odd in the data, so its
  S/N is exactly minus this one). :func:`search_false_positives` makes them from the files
  above, so a campaign runs it in a worker while the next group is being prepared;
* ``background.npz`` (with a false-alarm budget): the false-alarm background of the group
  (:mod:`.far_budget`), made in a worker the same way.
"""
from __future__ import annotations

import json
import logging
import mmap
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from astropy.table import Table
from sotodlib import core
from sotodlib.preprocess import Pipeline

from so_transients.preprocess import step_fields
from so_transients.preprocess.sotodlib_steps import sotodlib_name
from so_transients.detect.find import FindConfig
from so_transients.detect.error_scale import ErrorScale, Sources, measure_error_scales
from so_transients.detect.fit import FitConfig, FitInputs
from so_transients.campaign.noise_model import NoiseModel
from so_transients.campaign.pca_response import PcaResponse, model_signal_filter
from so_transients.common.pointing import BORE_Q, boresight_q
from so_transients.sim.imperfections import respond_to_sky
from so_transients.sim.simulate import planned_detsets, simulate
from so_transients.campaign.search_steps import SEARCH_STEPS, SearchSteps, step_settings

log = logging.getLogger(__name__)
#: ``info.json``'s ``format``: a group prepared in another format is prepared again (2: the
#: PCA's weights and mask limits are kept for the fast path, :mod:`.pca_response`; 3: the
#: filter's own ``n_eff`` per detector; 4: the fit's error scale in each scan direction)
PREPARED_FORMAT = 4
KEEP_FIELDS = ("timestamps", "boresight", "focal_plane", "det_info", "obs_info", "flags",
               "transient_filter", BORE_Q, "iir_params", "transient_pca_filter",
               "transient_pca_mask")


@dataclass(frozen=True)
class Group:
    obs_id: str
    wafer: str
    band: str

    @property
    def label(self) -> str:
        return f"{self.obs_id}_{self.wafer}_{self.band}"


def campaign_groups(cfg) -> list:
    """Every (observation, wafer, band) group of the noise-only simulation in the campaign's
    bands, known before anything is simulated."""
    return [Group(obs_id, *detset.split("_"))
            for obs_id, detsets in planned_detsets(cfg.sim).items()
            for detset in detsets if detset.split("_")[1] in cfg.bands]


def simulate_group(sim_config, root, group: Group, digest: str) -> str:
    """The noise-only dataset of one group (its context.yaml), simulated into ``root`` unless
    ``root`` holds it for ``digest`` already. The group's data are those of the whole
    simulation (see :func:`~so_transients.sim.simulate.simulate`'s ``detsets``)."""
    root = Path(root)
    stamp = root / "sim_digest.txt"
    context = root / "context.yaml"
    if context.exists() and stamp.exists() and stamp.read_text() == digest:
        return str(context)
    stamp.unlink(missing_ok=True)
    result = simulate(sim_config, output=root, overwrite=True, progress=False,
                      detsets=[f"{group.wafer}_{group.band}"])
    stamp.write_text(digest)
    return str(result.context)


def deconvolves_time_constants(standard_steps) -> bool:
    """Whether the standard steps deconvolve detector time constants (sotodlib's
    ``fourier_filter``, or its chunked ``transient_fourier_filter``, with ``timeconst_filter``
    inverted)."""
    for step in standard_steps:
        process = step.get("process") or {}
        params = process.get("filter_params") or {} if isinstance(process, dict) else {}
        if (sotodlib_name(step["name"]) == "fourier_filter"
                and process.get("filt_function") == "timeconst_filter"
                and params.get("invert", False)):
            return True
    return False


def _save_response(context, aman, folder):
    """``detectors.npz`` from the simulation's ``truth/detectors.ecsv`` (absent: ideal)."""
    truth = Path(context).parent / "truth" / "detectors.ecsv"
    if not truth.exists():
        return
    table = Table.read(truth)
    row = {name: i for i, name in enumerate(np.asarray(table["readout_id"]).astype(str))}
    idx = np.array([row[name] for name in np.asarray(aman.dets.vals).astype(str)])
    np.savez(folder / "detectors.npz", xi=np.asarray(table["xi_true"])[idx],
             eta=np.asarray(table["eta_true"])[idx], gain=np.asarray(table["gain"])[idx],
             tau=table["tau"].quantity.to_value("s")[idx])


def prepare_group(context, group: Group, standard_steps, search_steps, folder):
    """Filter one noise-only group, measure the fit's error scale and store the group's state
    in ``folder`` (see the module doc); returns ``info.json``'s content."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ctx = core.Context(str(context))
    aman = ctx.get_obs(group.obs_id, dets={"wafer_slot": group.wafer, "bandpass": group.band})
    Pipeline(standard_steps, logger=log).run(aman)
    boresight_q(aman)
    duration = float(aman.timestamps[-1] - aman.timestamps[0])
    np.save(folder / "snr.npy", np.asarray(aman.transient_snr, np.float32))
    live = np.flatnonzero(~np.asarray(aman.transient_filter.dead, bool))
    data = FitInputs.from_aman(aman, step_settings(search_steps, FindConfig).speed_tolerance)
    scale = measure_error_scales(data, live, Sources.none(),
                                 step_settings(search_steps, FitConfig))
    for name in [n for n in aman._fields if n not in KEEP_FIELDS]:
        aman.move(name, None)
    aman.save(str(folder / "state.h5"), overwrite=True)
    _save_response(context, aman, folder)
    noise_rms = float(np.median(np.asarray(aman.transient_filter.noise_level)[live]))
    info = dict(format=PREPARED_FORMAT, error_scale=scale.as_list(), duration=duration,
                n_dets=int(aman.dets.count), noise_rms=noise_rms,
                tau_deconvolved=deconvolves_time_constants(standard_steps),
                pca_lowpass=model_signal_filter(standard_steps)[1])
    (folder / "info.json").write_text(json.dumps(info, indent=1))
    return info


def search_false_positives(group: Group, folder, search_steps, inverted=True, stamp=""):
    """Run the search steps on a prepared group's noise-only S/N and on its sign-inverted
    copy; writes ``false_noise.ecsv``, ``false_inverted.ecsv`` and, last (it marks the search
    done), ``false_positives.json`` with their counts and ``stamp``. Returns the counts."""
    folder = Path(folder)
    state = GroupState.load(group, folder, search_steps)
    aman = state.aman
    aman.wrap("transient_snr", np.array(state.snr), [(0, "dets"), (1, "samps")])   # a copy
    search = SearchSteps(search_steps, error_scale=state.error_scale)
    fitted = {"noise": search.run(aman, group.obs_id, fitted=True)}
    aman.transient_snr[:] *= -1
    fitted["inverted"] = search.run(aman, group.obs_id, fitted=True) if inverted else Table()
    for kind, table in fitted.items():
        table.write(folder / f"fitted_{kind}.ecsv", overwrite=True)
    noise, flipped = (t[np.asarray(t["detected"], bool)] if len(t) else t
                      for t in fitted.values())
    noise.write(folder / "false_noise.ecsv", overwrite=True)
    flipped.write(folder / "false_inverted.ecsv", overwrite=True)
    counts = dict(n_false_noise=len(noise), n_false_inverted=len(flipped),
                  inverted=bool(inverted), stamp=stamp)
    (folder / "false_positives.json").write_text(json.dumps(counts, indent=1))
    return counts


def false_positives_done(folder, inverted, stamp) -> bool:
    """Whether :func:`search_false_positives` finished in ``folder`` with these settings."""
    path = Path(folder) / "false_positives.json"
    if not path.exists() or not (Path(folder) / "fitted_noise.ecsv").exists():
        return False
    done = json.loads(path.read_text())
    return done.get("stamp") == stamp and done.get("inverted") == bool(inverted)


def group_info(folder) -> dict:
    """``info.json`` of a prepared group, with the false-positive counts once searched."""
    folder = Path(folder)
    info = json.loads((folder / "info.json").read_text())
    if (folder / "false_positives.json").exists():
        info.update(json.loads((folder / "false_positives.json").read_text()))
    return info


def _slim(aman):
    """Drop what the search steps never read (their declarations in
    :mod:`so_transients.preprocess.step_fields`), so that cutting a window out of the group's
    AxisManager, and every merge into the window, stays cheap."""
    for name, keep in step_fields.kept_fields(SEARCH_STEPS).items():
        if name not in aman._fields or "*" in keep:
            continue
        sub = aman[name]
        for field in [f for f in sub._fields if f not in keep]:
            sub.move(field, None)
    if "iir_params" in aman._fields:
        aman.move("iir_params", None)


def _read_ahead(array):
    """Ask the kernel to read a memory-mapped array into the page cache now, in the
    background and in order: windows are then cut from memory instead of each costing disk
    seeks (half of an injection's time when the noise S/N was not cached)."""
    mapped = getattr(array, "_mmap", None)
    if mapped is not None and hasattr(mmap, "MADV_WILLNEED"):
        mapped.madvise(mmap.MADV_WILLNEED)
    return array


@dataclass
class Response:
    """How the group's detectors see the sky: true positions, gains and time constants (the
    metadata's positions and unit gains for an ideal simulation). ``apply_tau`` is False when
    the standard steps deconvolve the time constants again."""

    xi: np.ndarray
    eta: np.ndarray
    gain: np.ndarray
    tau: np.ndarray
    apply_tau: bool

    @classmethod
    def load(cls, folder, xi, eta, info):
        path = Path(folder) / "detectors.npz"
        if not path.exists():
            return cls(xi, eta, np.ones(len(xi)), np.zeros(len(xi)), False)
        saved = np.load(path)
        return cls(saved["xi"], saved["eta"], saved["gain"], saved["tau"],
                   not info.get("tau_deconvolved", False))

    def observe(self, signal, dets, sample_rate):
        """``signal`` (rows: detectors ``dets``) as the detectors record it, in place
        (:func:`so_transients.sim.imperfections.respond_to_sky`)."""
        tau = self.tau[dets] if self.apply_tau else np.zeros(len(dets))
        respond_to_sky(signal, SimpleNamespace(gain=self.gain[dets], tau=tau), 1.0 / sample_rate)


@dataclass
class GroupState:
    """A prepared noise-only group, as the injections use it."""

    group: Group
    aman: core.AxisManager
    snr: np.ndarray            # memory-mapped (dets, samps)
    model: NoiseModel
    error_scale: ErrorScale
    timestamps: np.ndarray
    bore_q: np.ndarray
    xi: np.ndarray
    eta: np.ndarray
    sigma_amp: np.ndarray
    search_steps: list         # the config entries of the search steps to run
    response: Response = None  # how the detectors see an injected source
    pca: PcaResponse = None    # what the standard steps' PCA takes of it (None: no PCA)

    @classmethod
    def load(cls, group: Group, folder, search_steps):
        folder = Path(folder)
        aman = core.AxisManager.load(str(folder / "state.h5"))
        info = group_info(folder)
        model = NoiseModel.from_aman(aman)
        pca = PcaResponse.from_aman(aman, info.get("pca_lowpass"))
        for name in ("transient_pca_filter", "transient_pca_mask"):
            if name in aman._fields:       # the search never reads them
                aman.move(name, None)
        _slim(aman)
        xi, eta = np.asarray(aman.focal_plane.xi), np.asarray(aman.focal_plane.eta)
        return cls(group, aman, _read_ahead(np.load(folder / "snr.npy", mmap_mode="r")),
                   model, ErrorScale.of(info["error_scale"]),
                   np.asarray(aman.timestamps), np.asarray(aman[BORE_Q]), xi, eta,
                   np.asarray(aman.transient_filter.sigma_amp), search_steps,
                   Response.load(folder, xi, eta, info), pca)

    @property
    def footprint(self):
        """(centre (xi, eta), radius) of the group's detectors in the focal plane."""
        centre = (float(self.xi.mean()), float(self.eta.mean()))
        return centre, float(np.hypot(self.xi - centre[0], self.eta - centre[1]).max())

    def window(self, dets, lo, hi, extra_snr=None, rows=()):
        """The group's AxisManager restricted to detectors ``dets`` (sorted indices) and
        samples ``lo:hi``, with ``transient_snr`` = noise S/N plus ``extra_snr`` on ``rows``
        (indices into ``dets``), only where the noise S/N is valid."""
        axes = [core.LabelAxis("dets", np.asarray(self.aman.dets.vals)[dets]),
                core.OffsetAxis("samps", hi - lo, self.aman.samps.offset + lo)]
        win = self.aman.restrict_axes(axes, in_place=False)
        snr = np.asarray(self.snr[dets, lo:hi])     # a copy (fancy indexing)
        if extra_snr is not None and len(rows):
            snr[rows] += np.asarray(extra_snr, np.float32) * (snr[rows] != 0)
        win.wrap("transient_snr", snr, [(0, "dets"), (1, "samps")])
        return win
