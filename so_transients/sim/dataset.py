"""Writing a simulated dataset that ``sotodlib.core.Context`` opens like real SO data.

A dataset folder holds::

    context.yaml                  imports so_transients; obs_loader_type: so_transients
    obsdb.sqlite                  ObsDb: one row per observation (one per tube and time block)
    obsfiledb.sqlite              ObsFileDb: detsets (one per wafer and band) and TOD files
    tod/<obs_id>/<obs_id>_<detset>.h5
    metadata/det_info.{h5,sqlite} det_info fields (wafer_slot, tube_slot, bandpass, det_id, pol,
                                  pixel) through a ManifestDb, merged into det_info
    metadata/focal_plane.{h5,sqlite}  xi, eta, gamma (radians) through a ManifestDb
    metadata/det_cal.{h5,sqlite}  detector time constants: tau_eff (s) as SO's det_cal (0 without)
                                  (``aman.det_cal.tau_eff``, what sotodlib's timeconst_filter reads)
    truth/flares.ecsv, truth/point_sources.ecsv, truth/glitches.ecsv, and with the instrument's
    imperfections or moving sources: truth/detectors.ecsv, truth/jumps.ecsv,
    truth/moving_sources.ecsv, truth/moving_source_tracks.ecsv
    sim_config.yaml               the configuration (with its seed) that produced it

Every path inside the dataset is relative to the file naming it (context.yaml's databases to
the context's folder, as ``sotodlib.core.Context`` resolves them; the ObsFileDb's and the
ManifestDbs' files to their database's folder), so a copied or moved folder reads itself.
"""
from __future__ import annotations

import os
from pathlib import Path

import yaml
from sotodlib.core import metadata
from sotodlib.io.metadata import write_dataset

from so_transients.io.loader import LOADER_NAME

DET_INFO_FIELDS = ("det_id", "tube_slot", "wafer_slot", "bandpass", "pol", "pixel")
OBS_COLUMNS = ["timestamp float", "duration float", "start_time float", "stop_time float",
               "n_samples int", "sample_rate float", "telescope str", "tube_slot str",
               "tube_flavor str", "wafer_slots_list str", "type str", "subtype str",
               "el_nom float", "az_center float", "az_throw float", "scan_speed float"]


def obs_id_for(start: float, tube_slot: str) -> str:
    """SO-style observation id of one tube: ``obs_<ctime>_lat<tube>_111``."""
    return f"obs_{int(start)}_lat{tube_slot}_111"


class DatasetWriter:
    """Accumulates observations, detsets and metadata, then writes the databases and context."""

    def __init__(self, root):
        self.root = Path(root)
        for sub in ("tod", "metadata", "truth"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self.obsdb = metadata.ObsDb()
        self.obsdb.add_obs_columns(OBS_COLUMNS)
        self.obsfiledb = metadata.ObsFileDb()
        self._detsets = set()
        scheme = metadata.ManifestScheme().add_exact_match("obs:obs_id").add_data_field("dataset")
        self.det_info_db = metadata.ManifestDb(scheme=scheme)
        scheme = metadata.ManifestScheme().add_exact_match("obs:obs_id").add_data_field("dataset")
        self.focal_plane_db = metadata.ManifestDb(scheme=scheme)
        self.det_cal_db = None     # made by the first observation with time constants
        self._metadata_written = set()

    def tod_path(self, obs_id, detset) -> Path:
        folder = self.root / "tod" / obs_id
        folder.mkdir(parents=True, exist_ok=True)
        return folder / f"{obs_id}_{detset}.h5"

    def add_observation(self, obs_id, info: dict):
        self.obsdb.update_obs(obs_id, info)

    def add_detset_file(self, obs_id, detset, readout_ids, path, n_samples):
        if detset not in self._detsets:
            self.obsfiledb.add_detset(detset, list(readout_ids))
            self._detsets.add(detset)
        rel = os.path.relpath(path, self.root)
        self.obsfiledb.add_obsfile(rel, obs_id, detset, 0, int(n_samples))

    def add_detector_metadata(self, obs_id, tube_slot, dets: dict, tau=None):
        """det_info and focal_plane entries of ``obs_id`` (the detectors of its tube), and
        det_cal's ``tau_eff`` (s, one per detector) when ``tau`` is given."""
        address = f"tube_{tube_slot}"
        if tau is not None:
            self._add_det_cal(obs_id, address, dets["readout_id"], tau)
        if address not in self._metadata_written:
            info = metadata.ResultSet(["dets:readout_id"] + [f"dets:{k}" for k in DET_INFO_FIELDS])
            info.rows = [tuple(row) for row in zip(dets["readout_id"],
                                                   *[dets[k] for k in DET_INFO_FIELDS])]
            write_dataset(info, str(self.root / "metadata/det_info.h5"), address, overwrite=True)
            fp = metadata.ResultSet(["dets:readout_id", "xi", "eta", "gamma"])
            fp.rows = [tuple(row) for row in zip(dets["readout_id"], dets["xi"], dets["eta"],
                                                 dets["gamma"])]
            write_dataset(fp, str(self.root / "metadata/focal_plane.h5"), address, overwrite=True)
            self._metadata_written.add(address)
        self.det_info_db.add_entry({"obs:obs_id": obs_id, "dataset": address},
                                   filename="det_info.h5")
        self.focal_plane_db.add_entry({"obs:obs_id": obs_id, "dataset": address},
                                      filename="focal_plane.h5")

    def _add_det_cal(self, obs_id, address, readout_ids, tau):
        if self.det_cal_db is None:
            scheme = (metadata.ManifestScheme().add_exact_match("obs:obs_id")
                      .add_data_field("dataset"))
            self.det_cal_db = metadata.ManifestDb(scheme=scheme)
        if address not in self._metadata_written:
            cal = metadata.ResultSet(["dets:readout_id", "tau_eff"])
            cal.rows = [(rid, float(t)) for rid, t in zip(readout_ids, tau)]
            write_dataset(cal, str(self.root / "metadata/det_cal.h5"), address, overwrite=True)
        self.det_cal_db.add_entry({"obs:obs_id": obs_id, "dataset": address},
                                  filename="det_cal.h5")

    def finish(self, config_dict: dict) -> Path:
        """Write databases, context.yaml and the config; returns the context.yaml path."""
        self.obsdb.to_file(str(self.root / "obsdb.sqlite"))
        self.obsfiledb.to_file(str(self.root / "obsfiledb.sqlite"))
        self.det_info_db.to_file(str(self.root / "metadata/det_info.sqlite"))
        self.focal_plane_db.to_file(str(self.root / "metadata/focal_plane.sqlite"))
        if self.det_cal_db is not None:
            self.det_cal_db.to_file(str(self.root / "metadata/det_cal.sqlite"))
        context = {
            "imports": ["so_transients"],
            "tags": {},                 # none needed: paths are relative to this file
            "obsdb": "obsdb.sqlite",
            "obsfiledb": "obsfiledb.sqlite",
            "obs_loader_type": LOADER_NAME,
            "metadata": [
                {"db": "metadata/det_info.sqlite", "det_info": True,
                 "loader": "ResultSetHdf"},
                {"db": "metadata/focal_plane.sqlite", "label": "focal_plane",
                 "unpack": "focal_plane", "loader": "ResultSetHdf"},
            ],
        }
        if self.det_cal_db is not None:
            context["metadata"].append({"db": "metadata/det_cal.sqlite",
                                        "label": "det_cal", "unpack": "det_cal",
                                        "loader": "ResultSetHdf"})
        path = self.root / "context.yaml"
        with open(path, "w") as f:
            yaml.safe_dump(context, f, sort_keys=False)
        with open(self.root / "sim_config.yaml", "w") as f:
            yaml.safe_dump(config_dict, f, sort_keys=False)
        return path
