"""Dispatching independent work through sotodlib's executor.

``sotodlib.utils.procs_pool.get_exec_env`` gives a process pool on one machine and
``mpi4py.futures`` under ``mpirun`` (rank 0 runs the caller; the other ranks serve as
workers and get no pool). Used by the campaign, ``so-transients events`` and the vetting
pages. A local pool's workers end with the process that made them, however it ends (a
SIGTERM, SIGKILL or the kernel's out-of-memory killer): none is left running a unit of a
campaign nobody waits for.
"""
from __future__ import annotations

import concurrent.futures
import ctypes
import multiprocessing
import os
import signal
import sys

from tqdm.auto import tqdm


#: Variables MPI launchers set to the number of ranks (Open MPI, MPICH / Intel MPI, PMIx).
MPI_SIZE_VARIABLES = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_SIZE")


def under_mpi() -> bool:
    """Whether this process is one of several MPI ranks (from the launcher's variables)."""
    return any(int(os.environ.get(k, "1") or 1) > 1 for k in MPI_SIZE_VARIABLES)


def executor(nproc):
    """(executor, as_completed) from sotodlib's ``get_exec_env``; None for one process.
    Under ``mpirun`` the ranks are the workers whatever ``nproc`` says (rank 0 gets the
    executor, the others None): every rank running the whole job would write the same files."""
    if nproc <= 1 and not under_mpi():
        return None, None
    from sotodlib.utils.procs_pool import get_exec_env

    try:
        _, pool, as_completed = get_exec_env(nprocs=nproc)
    except RuntimeError:   # the start method was already set in this process (a second run)
        pool = concurrent.futures.ProcessPoolExecutor(
            nproc, mp_context=multiprocessing.get_context("spawn"))
        as_completed = concurrent.futures.as_completed
    if isinstance(pool, concurrent.futures.ProcessPoolExecutor):
        pool = OwnedPool(pool)
    return pool, as_completed


#: Linux's ``prctl`` option that sends a process a signal when its parent ends.
PR_SET_PDEATHSIG = 1


class OwnedPool:
    """A local process pool whose workers are killed when this process ends: every task
    first asks the kernel (``prctl(PR_SET_PDEATHSIG, SIGKILL)``, Linux) to kill its worker
    once the parent is gone, and a worker whose parent is already gone ends at once.
    Everything but ``submit`` is the wrapped pool's."""

    def __init__(self, pool: concurrent.futures.ProcessPoolExecutor):
        self.pool = pool
        self.parent = os.getpid()

    def submit(self, fn, /, *args, **kwargs):
        return self.pool.submit(_owned_call, self.parent, fn, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.pool, name)


def _owned_call(parent, fn, *args, **kwargs):
    die_with_parent(parent)
    return fn(*args, **kwargs)


def die_with_parent(parent: int):
    """Make this process end when ``parent`` (its parent's pid) ends; end now if it has
    already (between the worker's start and this call). Does nothing off Linux."""
    if not sys.platform.startswith("linux"):
        return
    if not getattr(die_with_parent, "armed", False):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
        die_with_parent.armed = True
    if os.getppid() != parent:
        os._exit(1)


def is_worker_rank(pool, nproc) -> bool:
    """Whether :func:`executor` made this process an MPI worker rank (it has served work
    units until rank 0 finished, and must not run the job itself)."""
    return pool is None and (nproc > 1 or under_mpi())


def run_all(func, specs, desc, progress=True, pool=None, as_completed=None, unit="unit"):
    """``func(spec)`` for every spec, in ``pool`` if given (else here, one after the other),
    with a progress bar; returns the results in the order they finish."""
    bar = tqdm(total=len(specs), desc=desc, unit=unit, disable=not progress)
    done = []
    try:
        if pool is None:
            for spec in specs:
                done.append(func(spec))
                bar.update()
        else:
            futures = [pool.submit(func, spec) for spec in specs]
            for future in as_completed(futures):
                done.append(future.result())
                bar.update()
    finally:
        bar.close()
    return done
