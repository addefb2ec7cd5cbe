"""Dispatching independent work through sotodlib's executor.

``sotodlib.utils.procs_pool.get_exec_env`` gives a process pool on one machine and
``mpi4py.futures`` under ``mpirun`` (rank 0 runs the caller; the other ranks serve as
workers and get no pool). Used by the campaign and by ``so-transients events``.
"""
from __future__ import annotations

import concurrent.futures
import multiprocessing

from tqdm.auto import tqdm


def executor(nproc):
    """(executor, as_completed) from sotodlib's ``get_exec_env``; None for one process."""
    if nproc <= 1:
        return None, None
    from sotodlib.utils.procs_pool import get_exec_env

    try:
        _, pool, as_completed = get_exec_env(nprocs=nproc)
    except RuntimeError:   # the start method was already set in this process (a second run)
        pool = concurrent.futures.ProcessPoolExecutor(
            nproc, mp_context=multiprocessing.get_context("spawn"))
        as_completed = concurrent.futures.as_completed
    return pool, as_completed


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
