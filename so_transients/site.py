"""Running sotodlib's site preprocess pipeline on a dataset with the transient steps."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import yaml

TEMPLATE = Path(__file__).resolve().parent.parent / "configs" / "preprocess_transients.yaml"


def archive_index(archive_or_config) -> Path:
    """The archive index path, from an index (.sqlite) or a preprocess config (.yaml)."""
    path = Path(archive_or_config)
    if path.suffix in (".yaml", ".yml"):
        with open(path) as f:
            return Path(yaml.safe_load(f)["archive"]["index"])
    return path


def site_config(dataset, template=TEMPLATE, overrides=None) -> dict:
    """The preprocess config ``template`` pointed at ``dataset`` (its context.yaml), with the
    archive and plots in ``<dataset>/preprocess``. ``overrides``: {step name: {section: dict}}
    merged into the matching ``process_pipe`` entries."""
    dataset = Path(dataset).resolve()
    with open(template) as f:
        cfg = yaml.safe_load(f)
    out = dataset / "preprocess"
    cfg["context_file"] = str(dataset / "context.yaml")
    cfg["plot_dir"] = str(out / "plots")
    cfg["archive"]["index"] = str(out / "process_archive.sqlite")
    cfg["archive"]["policy"]["filename"] = str(out / "preprocess_archive.h5")
    apply_overrides(cfg["process_pipe"], overrides)
    return cfg


def apply_overrides(process_pipe, overrides=None):
    """Merge ``overrides`` ({step name: {section: dict or value}}) into the matching entries
    of ``process_pipe`` in place: dict sections are updated, other values replaced."""
    for step in process_pipe:
        for section, values in (overrides or {}).get(step["name"], {}).items():
            if isinstance(values, dict) and isinstance(step.get(section), dict):
                step[section].update(values)
            else:
                step[section] = values
    return process_pipe


def write_site_config(dataset, path=None, template=TEMPLATE, overrides=None) -> Path:
    """Write :func:`site_config` to ``path`` (default ``<dataset>/preprocess.yaml``)."""
    cfg = site_config(dataset, template, overrides)
    path = Path(path or Path(dataset) / "preprocess.yaml")
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        yaml.safe_dump(cfg, f, sort_keys=False)
    return path


#: Variables an MPI launcher (MPICH's hydra, Open MPI, PMIx) sets for its ranks.
MPI_LAUNCHER_PREFIXES = ("PMI_", "PMIX_", "OMPI_", "HYDRA_", "MPI_LOCALNRANKS",
                         "MPI_LOCALRANKID")


def standalone_env():
    """This process's environment without its MPI launcher's variables: a subprocess started
    from an MPI rank would otherwise try to join that rank's job and fail at MPI start-up."""
    return {k: v for k, v in os.environ.items() if not k.startswith(MPI_LAUNCHER_PREFIXES)}


def run_site_pipeline(config_path, nproc=1, extra_args=(), check=True):
    """``python -m sotodlib.site_pipeline.preprocess_tod CONFIG`` in a subprocess.

    The progress-bar file (pb_<ctime>.txt) goes next to the archive index, not into the
    working directory.

    The site pipeline logs failed groups to ``errlog.txt`` next to the archive index and still
    exits 0, so callers must inspect the archive (see :mod:`so_transients.results`). It runs
    as its own job even when called from an MPI rank (:func:`standalone_env`).
    """
    env = standalone_env()
    env.setdefault("OMP_WAIT_POLICY", "passive")
    env.setdefault("OMP_NUM_THREADS", "1")
    archive_dir = archive_index(config_path).parent
    archive_dir.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "sotodlib.site_pipeline.preprocess_tod", str(config_path),
           "--nproc", str(nproc), "--verbosity", "1",
           "--pb-path", str(archive_dir), *extra_args]
    return subprocess.run(cmd, env=env, check=check, capture_output=True, text=True)


def failed_groups(config_path) -> str:
    """Text of the site pipeline's errlog (failed groups), '' when none failed."""
    errlog = archive_index(config_path).parent / "errlog.txt"
    return errlog.read_text() if errlog.exists() else ""
