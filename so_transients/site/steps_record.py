"""Which steps made each group of an archive, so that results never outlive their config.

sotodlib's site pipeline skips every group its archive already holds, whatever the config
now says: edit a step's key and rerun, and the old results come back under the new config's
name. ``so-transients run`` therefore records, beside the archive index
(``<index stem>.steps.json``), the SHA-256 of the steps that made each group
(:func:`steps_hash`: ``process_pipe`` and ``subobs`` in canonical form, paths and file names
left out). Before a run, groups archived with other steps, or with none recorded (made
outside ``run``), are :func:`stale_groups`; ``run`` refuses them, naming them, unless told to
recompute (``--overwrite``: :func:`clear_archive`).
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

from so_transients.site.pipeline import ERRLOG, archive_index, read_config
from so_transients.site.results import archive_entries, archive_files, group_fields, group_keys


def steps_hash(config) -> str:
    """SHA-256 (hex) of the config's ``process_pipe`` and ``subobs``, in canonical JSON."""
    cfg = read_config(config)
    text = json.dumps({"process_pipe": cfg.get("process_pipe"), "subobs": cfg.get("subobs")},
                      sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def record_path(config) -> Path:
    index = archive_index(config)
    return index.with_name(index.stem + ".steps.json")


def _key(obs_id, group) -> str:
    return f"{obs_id} {'/'.join(group)}"


def archived_groups(config) -> list:
    """(obs_id, group tuple) of every group the archive of ``config`` holds ([] without
    an archive)."""
    index = archive_index(config)
    if not index.is_file():
        return []
    entries = archive_entries(index)
    return sorted(group_keys(entries, group_fields(config, entries)))


def recorded(config) -> dict:
    """{"obs_id group": steps hash} of the groups a run recorded."""
    path = record_path(config)
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not a steps record ({exc}): delete it and rerun with "
                         "--overwrite") from None


def stale_groups(config) -> list:
    """``"obs_id group"`` of the archived groups that the config's steps did not make (made
    with other steps, or with none recorded)."""
    want, have = steps_hash(config), recorded(config)
    return [_key(*g) for g in archived_groups(config) if have.get(_key(*g)) != want]


def record_groups(config, remade=False):
    """Record the config's steps for every archived group that has no record yet (those
    this run made; a stale group was refused or cleared before it), or with ``remade`` (the
    site pipeline's ``--overwrite`` made them all again) for every archived group."""
    want, have = steps_hash(config), recorded(config)
    for group in archived_groups(config):
        if remade:
            have[_key(*group)] = want
        else:
            have.setdefault(_key(*group), want)
    record_path(config).write_text(json.dumps(have, indent=1, sort_keys=True))


def clear_archive(config) -> list:
    """Delete the archive of ``config`` (index, its HDF5 files, errlog and steps record) so
    that every group is made again; returns the paths deleted."""
    index, _, files = archive_files(config)
    gone = []
    candidates = [index, record_path(config), index.parent / ERRLOG, *files]
    for path in candidates:
        if path.is_file():
            path.unlink()
            gone.append(path)
    return gone
