"""One run of ``so-transients events`` as the database ingests it: its tables read back, its
detections tied to their events, and the rows split by observation.

A run's folder holds ``events.ecsv``, ``lightcurves.ecsv`` and ``lightcurve_fits.ecsv`` (and,
since 0.9, ``cutouts.ecsv`` with the cutouts' FITS files); the
detections they were made from are the catalogue table (a file given, else ``detections.ecsv``
in the folder, beside the archive of the preprocess config named in the events' provenance,
where ``run`` and ``make demo`` write it, or next to the folder), else that archive itself.
Each detection's event is found again with the run's own association
(:func:`so_transients.events.tables.associate_detections`), and the events this gives must be
those of ``events.ecsv``: a detections table or association settings other than the run's are
refused, never half-matched.

An event is stored with the observation of its first detection, and its detections,
light-curve points and fits with it (:func:`split`): re-ingesting that observation replaces
all of them.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy.table import Table

from so_transients.common.tables import read_table
from so_transients.common.candidates import typed_table
from so_transients.events import schema as event_schema
from so_transients.events.association import AssociationConfig
from so_transients.events.tables import associate_detections
from so_transients.site.pipeline import archive_index
from so_transients.site.results import archive_table, read_catalogue, with_readable_columns

log = logging.getLogger(__name__)

#: The event tables of a run folder.
FILES = {"events": "events.ecsv", "lightcurves": "lightcurves.ecsv",
         "fits": "lightcurve_fits.ecsv"}
#: ... and those an older run's folder may lack (read as empty).
OPTIONAL_FILES = {"cutouts": ("cutouts.ecsv", event_schema.CUTOUTS)}


@dataclass
class Run:
    """The tables of one run; ``labels``: each detection's ``event_id``."""
    events: Table
    lightcurves: Table
    fits: Table
    detections: Table
    labels: np.ndarray
    obs_ids: list
    provenance: dict = field(default_factory=dict)
    folder: str = ""
    cutouts: Table = field(default_factory=lambda: typed_table(event_schema.CUTOUTS, {}))


@dataclass
class ObservationRows:
    """The rows stored with one observation (see the module)."""
    obs_id: str
    events: Table
    lightcurves: Table
    fits: Table
    detections: Table
    labels: np.ndarray
    cutouts: Table

    @property
    def t_first(self) -> float:
        """Its first event's time (inf without events), the order of ingestion."""
        return float(np.min(self.events["t_first"])) if len(self.events) else np.inf


def readable_columns() -> set:
    """The columns :func:`so_transients.site.results.with_readable_columns` adds to a
    catalogue (derived from others: not stored)."""
    from so_transients.common.candidates import table

    empty = table({"obs_id": np.zeros(0, str)}, first=("obs_id",))
    return set(with_readable_columns(empty).colnames) - set(empty.colnames)


def _read(path: Path, reader=read_table) -> Table:
    try:
        return reader(path)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read the table: {exc}") from None


def find_detections(folder: Path, provenance: dict, detections=None) -> tuple:
    """``(table, where)``: the detections of the run in ``folder`` (see the module)."""
    if detections is not None:
        return _read(Path(detections), read_catalogue), str(detections)
    config = provenance.get("preprocess_config", "")
    beside_archive = ([archive_index(config).parent / "detections.ecsv"]
                      if config and Path(config).is_file() else [])
    # the run's own table (where `run` writes it) before an older one next to the folder
    for path in (folder / "detections.ecsv", *beside_archive, folder.parent / "detections.ecsv"):
        if path.is_file():
            return _read(path, read_catalogue), str(path)
    if config and Path(config).is_file():
        return archive_table(config), f"the archive of {config}"
    raise FileNotFoundError(f"{folder}: no detections.ecsv in it or next to it, and the "
                            f"preprocess config of its provenance ({config or 'none'}) is not "
                            "there: give the detections table (so-transients catalog)")


def tie_detections(events: Table, detections: Table, cfg: AssociationConfig, where: str):
    """Each detection's ``event_id``, by the run's association; refuses detections that do
    not give exactly ``events``."""
    again, labels = associate_detections(detections, cfg)
    same = len(again) == len(events) and (
        np.array_equal(np.asarray(again["n_detections"]), np.asarray(events["n_detections"]))
        and np.allclose(again["t_first"], events["t_first"], rtol=0, atol=1e-3)
        and np.allclose(again["t_last"], events["t_last"], rtol=0, atol=1e-3))
    if not same:
        raise ValueError(f"the detections of {where} give {len(again)} event(s), not the "
                         f"{len(events)} of the events table: give the detections and the "
                         "association settings (events config) the run used")
    ids = np.asarray(events["event_id"], int)
    return ids[labels] if len(labels) else np.zeros(0, int)


def read_run(folder, detections=None, association: AssociationConfig | None = None) -> Run:
    """The run in events folder ``folder`` (``detections``: the catalogue table to use instead
    of finding it; ``association``: the run's association settings, default the defaults)."""
    folder = Path(folder)
    tables = {}
    for key, name in FILES.items():
        path = folder / name
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing (is {folder} the output folder of "
                                    "so-transients events?)")
        tables[key] = _read(path)
    for key, (name, columns) in OPTIONAL_FILES.items():
        path = folder / name
        tables[key] = _read(path) if path.is_file() else typed_table(columns, {})
    provenance = dict(tables["events"].meta.get("provenance", {}))
    dets, where = find_detections(folder, provenance, detections)
    derived = readable_columns() | {"event_id"}   # the events command's labels: tied again
    dets = dets[[c for c in dets.colnames if c not in derived]]
    if "detected" in dets.colnames:
        dets = dets[np.asarray(dets["detected"], bool)]
    labels = tie_detections(tables["events"], dets, association or AssociationConfig(), where)
    obs_ids = sorted({*map(str, provenance.get("obs_ids", [])), *map(str, dets["obs_id"]),
                      *map(str, tables["lightcurves"]["obs_id"])})
    return Run(tables["events"], tables["lightcurves"], tables["fits"], dets, labels, obs_ids,
               provenance, str(folder.resolve()), tables["cutouts"])


def owners(run: Run) -> dict:
    """{event_id: obs_id of its first detection}."""
    out = {}
    t = np.asarray(run.detections["t_peak"], float)
    for event_id in np.asarray(run.events["event_id"], int):
        mine = np.flatnonzero(run.labels == event_id)
        if not len(mine):
            raise ValueError(f"{run.folder}: event {event_id} has no detection")
        out[int(event_id)] = str(run.detections["obs_id"][mine[np.argmin(t[mine])]])
    return out


def split(run: Run) -> list:
    """One :class:`ObservationRows` per observation of the run (those without events too), in
    the order of their first event."""
    owner = owners(run)
    parts = []
    for obs_id in run.obs_ids:
        ids = np.array([e for e, o in owner.items() if o == obs_id], int)
        pick = lambda table: table[np.isin(np.asarray(table["event_id"], int), ids)]
        sel = np.isin(run.labels, ids)
        parts.append(ObservationRows(obs_id, pick(run.events), pick(run.lightcurves),
                                     pick(run.fits), run.detections[sel], run.labels[sel],
                                     pick(run.cutouts)))
    return sorted(parts, key=lambda p: (p.t_first, p.obs_id))
