"""Reading transient results back: one astropy table from a preprocess archive or observation.

Two ways in, both giving the same table:

* :func:`archive_table` walks the archive's ManifestDb and loads each group's saved
  AxisManager on its own (how sotodlib stores per-group outputs);
* :func:`observation_table` loads a whole observation through the Context (all groups
  concatenated along ``dets``), which works because candidates are stored on the detector axis
  (:mod:`so_transients.preprocess.slot_storage`).

The columns are those of :mod:`so_transients.common.candidates`, with their units (mJy for fluxes,
rad for positions, s of ctime for times) and descriptions, after ``obs_id``; both readers add
every angle in degrees (errors in arcseconds) and ``t_peak`` in UTC beside them
(:func:`with_readable_columns`). :func:`write_table` writes such a table with the provenance
block (:mod:`so_transients.site.provenance`) in ECSV, FITS or CSV, its angles in one unit only:
degrees (errors in arcseconds), the radian columns left out. :func:`read_catalogue` reads it back
as written (empty strings as ``''``, not masked) with the radians restored for the package's own
code (:func:`with_radian_columns`).

:func:`archive_status` says which groups are missing from an archive and why. sotodlib appends
to ``errlog.txt`` across runs; :func:`so_transients.site.pipeline.run_site_pipeline` moves an earlier
errlog aside, and :func:`archive_status` only reports errlog entries of groups that are not in
the archive, so a group that failed once and then succeeded is never reported as failed.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy.table import Column, Table, vstack
from sotodlib import core
from sotodlib.core.metadata import ManifestDb

from so_transients.common import candidates
from so_transients.common.angles import ARCSEC, DEG
from so_transients.common.tables import FORMATS, for_writing, read_table
from so_transients.common.times import utc
from so_transients.site.provenance import attach, provenance
from so_transients.site.pipeline import archive_index, check_config, errlog_entries, read_config
from so_transients.preprocess.slot_storage import unpack
from so_transients.site.selection import ObsSelection

#: Columns of every table read back, in order.
FIRST = ["obs_id"] + candidates.names(saved=True)


def amplitude(aman, dets=slice(None), lo=None, hi=None):
    """Amplitude timestream (signal units, mJy) of detectors ``dets``, samples ``lo:hi``: the
    S/N of ``transient_filter`` times each detector's ``sigma_amp``."""
    sigma = np.asarray(aman.transient_filter.sigma_amp, np.float32)[dets]
    return np.asarray(aman.transient_snr[dets, lo:hi]) * sigma[:, None]


def _empty_table() -> Table:
    return candidates.table({"obs_id": np.zeros(0, str), **candidates.empty()}, first=["obs_id"])


def proc_table(proc_aman, obs_id="", wafer_slot=None) -> Table:
    """Rows of every candidate stored in ``proc_aman`` (one group or several concatenated)."""
    parts = {name: unpack(proc_aman[name]) for name in candidates.STEPS
             if name in proc_aman._fields}
    base = parts.get("transient_find")
    if base is None or not len(base["cand_id"]):
        return _empty_table()
    rows = {}
    for name, part in parts.items():
        if not np.array_equal(part["cand_id"], base["cand_id"]):
            raise ValueError(f"{obs_id}: {name} is not aligned with transient_find")
        rows.update(part)
    rows.pop("det")
    n = len(base["cand_id"])
    rows["obs_id"] = np.full(n, obs_id)
    if "wafer_slot" not in rows:
        rows["wafer_slot"] = np.full(n, wafer_slot or "")
    return candidates.table(rows, first=["obs_id"])


def archive_entries(index_path):
    """(obs_id, group tags, absolute h5 filename, dataset) for every group in an archive."""
    index_path = Path(index_path)
    if not index_path.is_file():     # ManifestDb would create an empty one
        raise FileNotFoundError(f"{index_path}: no preprocess archive index (has the site "
                                "pipeline run with this config?)")
    db = ManifestDb(str(index_path))
    out = []
    for entry in db.inspect():
        filename = entry["filename"]
        if not os.path.isabs(filename):
            filename = str(index_path.parent / filename)
        tags = {k.split(":", 1)[1]: v for k, v in entry.items() if k.startswith("dets:")}
        out.append((entry["obs:obs_id"], tags, filename, entry["dataset"]))
    return out


def _public(table: Table, detected_only) -> Table:
    """What the readers return: the detections only unless not ``detected_only``, with
    :func:`with_readable_columns`."""
    if detected_only:
        table = table[np.asarray(table["detected"], bool)]
    return with_readable_columns(table)


def archive_table(archive_or_config, detected_only=True, obs_ids=None) -> Table:
    """Every group of every observation in an archive (of ``obs_ids`` only, when given), one
    group at a time, as one table (positions also in degrees: :func:`with_readable_columns`)."""
    tables = []
    for obs_id, tags, filename, dataset in archive_entries(archive_index(archive_or_config)):
        if obs_ids is not None and obs_id not in obs_ids:
            continue
        proc = core.AxisManager.load(filename, dataset)
        tables.append(proc_table(proc, obs_id, tags.get("wafer_slot")))
    table = vstack(tables) if tables else _empty_table()
    if not len(table):
        table = _empty_table()
    return _public(table, detected_only)


#: Per-group scalars sotodlib's Pipeline saves in every group (NaN without an IIR filter):
#: they differ (NaN != NaN) between groups, so a whole-observation load cannot merge them.
PER_GROUP_SCALARS = ("frequency_cutoffs",)


def _get_meta_dropping(context, obs_id, fields):
    """``context.get_meta(obs_id)`` with ``fields`` dropped from the preprocess archive's
    entry (the context itself is left as it was)."""
    entries = context["metadata"]
    context["metadata"] = [
        dict(e, drop_fields=list(e.get("drop_fields", [])) + list(fields))
        if "preprocess" in (e.get("name"), e.get("label"), e.get("unpack")) else e
        for e in entries]
    try:
        return context.get_meta(obs_id)
    finally:
        context["metadata"] = entries


def observation_table(context, obs_id, detected_only=True) -> Table:
    """The whole observation's candidates through the Context (all groups at once), with
    the columns of :func:`archive_table` (positions also in degrees).

    ``context`` must have the preprocess archive among its metadata (as
    ``sotodlib.preprocess.preprocess_util.get_preprocess_context`` arranges).
    """
    meta = _get_meta_dropping(context, obs_id, PER_GROUP_SCALARS)
    return _public(proc_table(meta.preprocess, obs_id), detected_only)


def config_of(archive_or_config):
    """The preprocess config of an archive: the .yaml given, or for an index the dataset's
    ``preprocess.yaml`` (two folders up) when it names that index; None when unknown."""
    path = Path(archive_or_config)
    if path.suffix in (".yaml", ".yml"):
        return path
    guess = path.resolve().parent.parent / "preprocess.yaml"
    if guess.is_file() and archive_index(guess).resolve() == path.resolve():
        return guess
    return None


def selected_obs(config, selection: ObsSelection | None) -> set | None:
    """obs_ids of the config's ObsDb that ``selection`` takes (None: no selection, all)."""
    if selection is None or selection.everything:
        return None
    return selection.obs_ids(core.Context(read_config(config)["context_file"]))


def expected_groups(config, selection: ObsSelection | None = None) -> set:
    """{(obs_id, group)} the site pipeline runs for ``config``: every observation of the
    ObsDb (or those ``selection`` takes) times the groups of its ``subobs.use`` fields (here
    one per wafer and band), as sotodlib's ``get_groups`` makes them (groups with a field
    ``NC`` are never run)."""
    from sotodlib.preprocess import preprocess_util as pp_util

    cfg = read_config(config)
    context = core.Context(cfg["context_file"])
    chosen = selected_obs(config, selection)
    out = set()
    for obs in context.obsdb.query():
        if chosen is not None and obs["obs_id"] not in chosen:
            continue
        _, groups, error = pp_util.get_groups(obs["obs_id"], cfg, context)
        if error[0] is not None:
            raise ValueError(f"{config}: {obs['obs_id']}: cannot list its groups: {error[1]}")
        out |= {(obs["obs_id"], tuple(str(g) for g in group)) for group in groups
                if "NC" not in group}
    return out


def group_fields(config, entries) -> list:
    """The ``subobs.use`` fields of ``config``, else the archive entries' tag names."""
    if config is not None:
        use = read_config(config).get("subobs", {}).get("use", "detset")
        return [u.split(":", 1)[-1] for u in np.atleast_1d(use)]
    return sorted(entries[0][1]) if entries else []


@dataclass
class ArchiveStatus:
    """What an archive holds against what the site pipeline should have made."""

    index: Path
    config: Path | None
    archived: set
    expected: set | None                    # None: no config to list them from
    failed: dict = field(default_factory=dict)   # {(obs_id, group): (error type, message)}

    @property
    def complete(self) -> bool:
        return not self.failed and (self.expected is None or self.expected <= self.archived)

    @property
    def obs_ids(self) -> list:
        return sorted({obs for obs, _ in (self.expected or set()) | self.archived})

    def report(self) -> str:
        """A few lines: groups expected, archived, and each failed one with its reason."""
        expected = "unknown (give the preprocess config)" if self.expected is None \
            else len(self.expected)
        lines = [f"Archive {self.index}: groups expected {expected}, in the archive "
                 f"{len(self.archived)}, failed {len(self.failed)}"]
        for (obs_id, group), (kind, message) in sorted(self.failed.items()):
            lines.append(f"  FAILED {obs_id} {'/'.join(group)}: {kind}: {message}")
        return "\n".join(lines)


def group_keys(entries, fields) -> set:
    """``(obs_id, group tuple)`` of archive ``entries`` (:func:`archive_entries`), the group
    as the values of ``fields`` (:func:`group_fields`)."""
    return {(obs, tuple(str(tags[f]) for f in fields)) for obs, tags, _, _ in entries}


def archive_status(archive_or_config, selection: ObsSelection | None = None) -> ArchiveStatus:
    """Groups expected (:func:`expected_groups`), archived, and failed with the reason from
    the errlog (groups in the errlog and not in the archive; with a config, also groups
    expected and in neither); with a ``selection`` (a config needed), of the observations
    it takes only."""
    config = config_of(archive_or_config)
    if config is not None:
        check_config(config)
    elif selection is not None and not selection.everything:
        raise ValueError(f"{archive_or_config}: selecting observations needs the preprocess "
                         "config (its ObsDb), not the archive index")
    index = archive_index(archive_or_config)
    entries = archive_entries(index)
    fields = group_fields(config, entries)
    chosen = selected_obs(config, selection) if config is not None else None
    take = (lambda obs: True) if chosen is None else (lambda obs: obs in chosen)
    archived = {key for key in group_keys(entries, fields) if take(key[0])}
    expected = expected_groups(config, selection) if config is not None else None
    errors = {k: v for k, v in errlog_entries(index.parent).items() if take(k[0])}
    missing = (expected or set()) - archived
    failed = {k: errors.get(k, ("missing", "not in the archive and not in errlog.txt"))
              for k in missing}
    failed.update({k: v for k, v in errors.items() if k not in archived})
    return ArchiveStatus(index, config, archived, expected, failed)


def readable_columns() -> list:
    """``(name, source, unit, scale, period, description)`` of the columns
    :func:`with_readable_columns` adds: every angle of the candidate schema (unit rad) in
    degrees as ``<name>_deg`` (a right ascension wrapped into [0, 360): ``period`` 360), or for
    an error in arcseconds as ``<name>_arcsec`` (``period`` None)."""
    out = []
    for col in candidates.columns(saved=True):
        if col.unit != "rad":
            continue
        if col.name.endswith("_err"):
            out.append((f"{col.name}_arcsec", col.name, "arcsec", ARCSEC, None,
                        f"{col.name} in arcseconds"))
        else:
            period = 360.0 if col.name.endswith("ra") else None
            out.append((f"{col.name}_deg", col.name, "deg", DEG, period,
                        f"{col.name} in degrees{' in [0, 360)' if period else ''}: "
                        f"{col.description}"))
    return out


def with_readable_columns(table: Table) -> Table:
    """A copy with every angle column (rad) also in degrees right after it (``ra_deg`` and
    ``cluster_ra_deg`` in [0, 360), ``dec_deg``, ``cluster_dec_deg``; errors in arcseconds:
    ``ra_err_arcsec``, ``dec_err_arcsec``; :func:`readable_columns`) and ``t_peak_utc`` (ISO
    UTC) after ``t_peak``; the radian and ctime columns are kept as the archive has them.
    Columns already there are recomputed from their source, so applying it twice changes
    nothing."""
    out = table.copy()
    for name, src, unit, scale, period, text in readable_columns():
        if src not in out.colnames:
            continue
        values = np.asarray(out[src], np.float64) / scale
        values = np.mod(values, period) if period else values
        _put(out, Column(values, name=name, unit=unit, description=text), after=src)
    if "t_peak" in out.colnames:
        _put(out, Column(utc(out["t_peak"]), name="t_peak_utc",
                         description="t_peak as ISO UTC"), after="t_peak")
    return out


def with_radian_columns(table: Table) -> Table:
    """A copy with the radian columns :func:`write_table` leaves out restored from their
    degree (error: arcsecond) companions, each right before it: the inverse of
    :func:`with_readable_columns` (a right ascension comes back in [0, 2 pi)); companions
    read without units (CSV) are given theirs."""
    out = table.copy()
    for name, src, unit, scale, period, _ in readable_columns():
        if name not in out.colnames or src in out.colnames:
            continue
        out[name].unit = unit
        text = candidates.BY_NAME[src].description
        values = np.asarray(out[name], np.float64) * scale
        out.add_column(Column(values, name=src, unit="rad", description=text),
                       index=out.colnames.index(name))
    return out


def read_catalogue(path) -> Table:
    """A table :func:`write_table` wrote (ECSV, FITS or CSV), as the package's code uses it:
    empty strings as ``''`` and the radian columns restored (:func:`with_radian_columns`)."""
    return with_radian_columns(read_table(path))


def _put(table: Table, column: Column, after):
    """Replace ``column`` in ``table`` or add it right after column ``after``."""
    if column.name in table.colnames:
        table.replace_column(column.name, column)
    else:
        table.add_column(column, index=table.colnames.index(after) + 1)


def output_format(path, overwrite=False) -> str:
    """The astropy format of ``path`` (by suffix); refuses an existing file unless
    ``overwrite``."""
    path = Path(path)
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: unknown table suffix {path.suffix!r}; use one of "
                         f"{sorted(FORMATS)}")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists: not overwritten (use --overwrite or another "
                              "file name)")
    return fmt


def write_table(table: Table, path, config=None, obs_ids=None, overwrite=False) -> Path:
    """Write ECSV, FITS or CSV (chosen by the suffix) with :func:`with_readable_columns`, its
    angles in degrees only (errors in arcseconds: the radian columns are left out; read it back
    with :func:`read_catalogue` to have them again), and the provenance of ``config`` and
    ``obs_ids`` (default: the table's) in the metadata.
    Booleans stay booleans in every format (FITS logical columns) and empty strings stay
    empty (:func:`so_transients.common.tables.for_writing`): read the file back with
    :func:`so_transients.common.tables.read_table` (any format) or, for ECSV, ``Table.read``.
    CSV carries the provenance as ``# key: value`` lines: with astropy alone read it with
    ``Table.read(path, format="ascii.csv", comment="#")`` (pandas: ``comment="#"``,
    ``keep_default_na=False``)."""
    path = Path(path)
    fmt = output_format(path, overwrite)
    obs_ids = table["obs_id"] if obs_ids is None else obs_ids
    readable = with_readable_columns(table)
    radians = [src for _, src, *_ in readable_columns() if src in readable.colnames]
    readable.remove_columns(radians)
    out = attach(readable, fmt, provenance(config, obs_ids))
    out, extra = for_writing(out, fmt)
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "ascii.csv":
        extra["comment"] = "# "
    out.write(path, format=fmt, overwrite=overwrite, **extra)
    return path


def archive_files(config_path) -> tuple:
    """``(index, folder, HDF5 files)`` of the archive ``config_path`` names: its index (which
    may not exist yet), the folder its policy writes in and the files it wrote there
    (``<stem>*<suffix>``: the ``simple`` policy's file and the numbered ones of later runs)."""
    cfg = read_config(config_path)
    policy = Path(cfg["archive"]["policy"]["filename"])
    return (Path(cfg["archive"]["index"]), policy.parent,
            sorted(policy.parent.glob(policy.stem + "*" + policy.suffix)))


def remove_orphans(config_path) -> list:
    """Groups of the archive's HDF5 files that its index does not name (a run stopped
    between writing a group and indexing it; sotodlib would fail to write it again with
    ``destination object already exists``), and files left in its ``temp/`` folder:
    deleted. Returns what was deleted, as ``file:group`` or file paths."""
    import h5py

    index, folder, files = archive_files(config_path)
    gone = []
    for leftover in sorted((folder / "temp").glob("*")):
        if leftover.is_file():
            leftover.unlink()
            gone.append(str(leftover))
    if not files:
        return gone
    named = {(Path(f).resolve(), d) for _, _, f, d in archive_entries(index)} \
        if index.is_file() else set()
    for path in files:
        with h5py.File(path, "a") as h5:
            for name in list(h5.keys()):
                if (path.resolve(), name) not in named:
                    del h5[name]
                    gone.append(f"{path}:{name}")
    return gone
