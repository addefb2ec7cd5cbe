"""Running sotodlib's site preprocess pipeline on a dataset with the transient steps.

The config :func:`write_site_config` writes names its paths (``context_file``,
``archive.index``, ``archive.policy.filename``, ``plot_dir``) relative to the config's own
folder, so that a copied or moved dataset reads and writes its own files. sotodlib resolves
them against the working directory: :func:`run_site_pipeline` (``so-transients run``) runs
the site pipeline from the config's folder, and :func:`read_config` gives every path
resolved against it. Run sotodlib's ``preprocess_tod`` yourself from that folder
(``cd DATASET``), and give ``get_preprocess_context`` the dict :func:`read_config` returns
(:func:`preprocess_context`). :func:`check_config` still refuses a config inside one dataset
whose absolute paths point at another.
"""
from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import yaml

#: the shipped configs (package data; the repository's ``configs`` links to them)
CONFIGS = Path(__file__).resolve().parents[1] / "configs"
#: a checkout's top folder (studies and their configs live there, not in the package)
REPOSITORY = Path(__file__).resolve().parents[2]
#: the production site config: coherent search with calibrated false-alarm rates
PRODUCTION = CONFIGS / "preprocess_production.yaml"
#: the reference paper's method (Clancy et al. 2025)
PAPER = CONFIGS / "preprocess_paper.yaml"
#: the config ``so-transients site-config`` writes by default
TEMPLATE = PRODUCTION


def archive_index(archive_or_config) -> Path:
    """The archive index path, from an index (.sqlite) or a preprocess config (.yaml)."""
    path = Path(archive_or_config)
    if path.suffix in (".yaml", ".yml"):
        return Path(read_config(path)["archive"]["index"])
    return path


#: The paths of a preprocess config, as key paths into it.
PATH_KEYS = (("context_file",), ("plot_dir",), ("archive", "index"),
             ("archive", "policy", "filename"))


def _map_paths(cfg, convert):
    """``cfg`` with each path of :data:`PATH_KEYS` it holds replaced by ``convert(path)``."""
    for keys in PATH_KEYS:
        node = cfg
        for key in keys[:-1]:
            node = node.get(key) if isinstance(node, dict) else None
        if isinstance(node, dict) and isinstance(node.get(keys[-1]), str):
            node[keys[-1]] = convert(node[keys[-1]])
    return cfg


def read_config(config_path) -> dict:
    """A preprocess config as a dict, each relative path (:data:`PATH_KEYS`) resolved against
    the config's folder; errors name the file."""
    try:
        with open(config_path) as f:
            cfg = yaml.safe_load(f)
    except yaml.YAMLError as exc:
        raise ValueError(f"{config_path}: not valid YAML: {exc}") from None
    if not isinstance(cfg, dict) or "archive" not in cfg or "context_file" not in cfg:
        raise ValueError(f"{config_path}: not a preprocess config (needs context_file and "
                         "archive)")
    folder = Path(config_path).resolve().parent
    return _map_paths(cfg, lambda p: str(folder / p) if not os.path.isabs(p) else p)


def preprocess_context(config_path):
    """``(configs, context)`` of sotodlib's ``get_preprocess_context`` for a config whose
    paths are relative to its folder (any working directory)."""
    from sotodlib.preprocess import preprocess_util as pp_util

    return pp_util.get_preprocess_context(read_config(config_path))


def dataset_context(dataset) -> Path:
    """``<dataset>/context.yaml``, or a ValueError when the folder holds no dataset."""
    context = Path(dataset).resolve() / "context.yaml"
    if not context.is_file():
        raise ValueError(f"{dataset}: no context.yaml, not a dataset folder (make one with "
                         "`so-transients simulate`)")
    return context


def check_config(config_path):
    """Refuse a config sitting in a dataset folder (next to a context.yaml) whose
    ``context_file`` is another dataset's: a copied dataset whose config still reads, and
    writes the archive of, the original."""
    config_path = Path(config_path)
    here = config_path.resolve().parent / "context.yaml"
    named = Path(read_config(config_path)["context_file"]).resolve()
    if here.is_file() and named != here:
        raise ValueError(f"{config_path}: context_file is {named}, not this dataset's {here} "
                         f"(copied or moved?): run `so-transients site-config "
                         f"{config_path.parent}` again")


def build_steps(config_path):
    """Build sotodlib's preprocess ``Pipeline`` of the config's ``process_pipe`` here, so that
    a misspelt key or a value out of range is refused (naming the step and key) before
    anything runs; the site pipeline itself builds it only for groups it has not made. (The
    transient steps are registered: importing any module of the package imports
    ``so_transients`` first.)"""
    from sotodlib.preprocess import Pipeline

    Pipeline(read_config(config_path)["process_pipe"])


def site_config(dataset, template=TEMPLATE, overrides=None, results=None) -> dict:
    """The preprocess config ``template`` pointed at ``dataset`` (its context.yaml), with the
    archive and plots in ``results`` (default ``<dataset>/preprocess``), as absolute paths
    (see the module's note). ``overrides``: {step name: {section: dict}} merged into the
    matching ``process_pipe`` entries."""
    dataset = dataset_context(dataset).parent
    with open(template) as f:
        cfg = yaml.safe_load(f)
    out = Path(results).resolve() if results is not None else dataset / "preprocess"
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


def write_site_config(dataset, path=None, template=TEMPLATE, overrides=None,
                      results=None) -> Path:
    """Write :func:`site_config` to ``path`` (default ``<dataset>/preprocess.yaml``), its
    paths relative to the config's folder (a copied dataset reads its own files)."""
    cfg = site_config(dataset, template, overrides, results)
    path = Path(path or Path(dataset) / "preprocess.yaml")
    path.parent.mkdir(parents=True, exist_ok=True)
    folder = path.resolve().parent
    _map_paths(cfg, lambda p: os.path.relpath(p, folder))
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


#: The site pipeline's log of failed groups, next to the archive index, and the previous run's.
ERRLOG = "errlog.txt"
PREVIOUS_ERRLOG = "errlog.prev.txt"


def run_site_pipeline(config_path, nproc=1, extra_args=(), check=True):
    """sotodlib's ``preprocess_tod`` on ``config_path`` in a subprocess (:mod:`.site_run`).

    The site pipeline logs failed groups to ``errlog.txt`` next to the archive index and still
    exits 0, so callers must inspect the archive (see :mod:`so_transients.site.results`). Each run
    starts a fresh errlog: an earlier one is moved to ``errlog.prev.txt``, so that groups which
    failed before and succeed now are not reported as failed. The progress-bar file
    (pb_<ctime>.txt) is written to a temporary folder and dropped, and an empty ``temp/`` left
    next to the archive is removed. It runs as its own job even when called from an MPI rank
    (:func:`standalone_env`).
    """
    check_config(config_path)
    env = standalone_env()
    env.setdefault("OMP_WAIT_POLICY", "passive")
    env.setdefault("OMP_NUM_THREADS", "1")
    archive_dir = archive_index(config_path).parent
    archive_dir.mkdir(parents=True, exist_ok=True)
    errlog = archive_dir / ERRLOG
    if errlog.exists():
        errlog.replace(archive_dir / PREVIOUS_ERRLOG)
    config_path = Path(config_path).resolve()
    with tempfile.TemporaryDirectory(prefix="so_transients_pb_") as pb_dir:
        cmd = [sys.executable, "-m", "so_transients.site.run", str(config_path),
               "--nproc", str(nproc), "--verbosity", "1", "--pb-path", pb_dir, *extra_args]
        try:       # from the config's folder: sotodlib resolves its paths against it
            # its own session: a signal to this process stops it and its workers too
            with subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True, cwd=config_path.parent,
                                  start_new_session=True) as proc, _owned(proc):
                out, err = proc.communicate()
            done = subprocess.CompletedProcess(cmd, proc.returncode, out, err)
            if check:
                done.check_returncode()
            return done
        finally:
            remove_empty_leftovers(config_path)


STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)


@contextlib.contextmanager
def _owned(proc):
    """While ``proc`` runs, a SIGTERM, SIGINT or SIGHUP to this process stops ``proc``'s
    whole process group (the site pipeline and its pool's workers: SIGTERM, then SIGKILL
    after 10 s) and then ends this process with status 128 + the signal's number. Only in
    the main thread (elsewhere signals cannot be caught, and nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        stop_group(proc)
        raise SystemExit(128 + signum)

    previous = {sig: signal.signal(sig, stop) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if proc.poll() is None:          # left by an exception: never orphaned
            stop_group(proc)


def stop_group(proc, grace=10.0):
    """SIGTERM to ``proc``'s process group, then SIGKILL to whatever is left of it after
    ``grace`` s (or once the leader is gone: its pool's workers)."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    try:
        proc.wait(grace)
    except subprocess.TimeoutExpired:
        pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def remove_empty_leftovers(config_path):
    """Remove the empty ``temp/`` folder sotodlib leaves next to the archive file."""
    policy_dir = Path(read_config(config_path)["archive"]["policy"]["filename"]).parent
    temp = policy_dir / "temp"
    if temp.is_dir() and not any(temp.iterdir()):
        temp.rmdir()


def failed_groups(config_path) -> str:
    """Text of the site pipeline's errlog (failed groups of the last run), '' when none."""
    errlog = archive_index(config_path).parent / ERRLOG
    return errlog.read_text() if errlog.exists() else ""


def errlog_entries(archive_dir) -> dict:
    """{(obs_id, group tuple): (error type, first line of the message)} from the errlog in
    ``archive_dir``; a group logged twice keeps its latest entry.

    sotodlib writes each failure as ``<ctime>, <obs_id>, <group list>, <error type>`` and a
    tab-indented message with its traceback."""
    errlog = Path(archive_dir) / ERRLOG
    entries, key = {}, None
    for line in (errlog.read_text().splitlines() if errlog.exists() else []):
        header = ERRLOG_HEADER.match(line)
        if header:
            key = (header["obs_id"], _group_tuple(header["group"]))
            entries[key] = (header["kind"], "")
        elif key is not None and line.startswith("\t") and not entries[key][1]:
            # the message, then the traceback on the same line: keep the message
            message = line.strip().split('  File "')[0].strip()
            entries[key] = (entries[key][0], message)
    return entries


#: A failure's first line in sotodlib's errlog: ``<ctime>, <obs_id>, <group>, <error type>``.
ERRLOG_HEADER = re.compile(r"^[\d.]+, (?P<obs_id>\S+), (?P<group>.*), (?P<kind>\w+)$")


def _group_tuple(text) -> tuple:
    """``['w16', 'f090']`` or ``[np.str_('w16'), ...]`` as written by sotodlib -> ('w16', 'f090')."""
    return tuple(re.findall(r"'([^']*)'", text))
