"""``python -m so_transients.site.run CONFIG [preprocess_tod options]``: sotodlib's site
pipeline ``preprocess_tod``, with its process pool shut down before the interpreter exits.

``sotodlib.site_pipeline.preprocess_tod.main`` takes a ``ProcessPoolExecutor`` from
``sotodlib.utils.procs_pool.get_exec_env`` and never shuts it down. At exit the pool is
garbage-collected: its manager thread closes its wake-up pipe while CPython 3.11's
``concurrent.futures.process._python_exit`` writes to it, and the run ends with
``Exception ignored in: <module 'threading'> ... OSError: [Errno 9] Bad file descriptor``
(harmless: every group is already saved). Running it through this module shuts the pool down
first; running sotodlib's module directly may still print that message.

It also runs from the config's folder, against which the paths of a config written by
``so-transients site-config`` are relative (sotodlib resolves them against the working
directory).
"""
from __future__ import annotations

import os
import sys

import so_transients  # noqa: F401  registers the transient steps and the obs loader


def main(argv=None):
    """Run ``preprocess_tod`` on ``argv`` (default: the command line), then shut down the
    executors it made."""
    from sotodlib.site_pipeline import preprocess_tod
    from sotodlib.site_pipeline.utils.pipeline import main_launcher
    from sotodlib.utils import procs_pool

    made = []

    def get_exec_env(*args, **kwargs):
        rank, executor, as_completed = procs_pool.get_exec_env(*args, **kwargs)
        made.append(executor)
        return rank, executor, as_completed

    preprocess_tod.get_exec_env = get_exec_env
    argv = list(sys.argv[1:] if argv is None else argv)
    config = next((a for a in argv if a.endswith((".yaml", ".yml")) and os.path.isfile(a)),
                  None)
    here = os.getcwd()
    if config is not None:
        argv[argv.index(config)] = os.path.abspath(config)
        os.chdir(os.path.dirname(os.path.abspath(config)))
    try:
        return main_launcher(preprocess_tod.main, preprocess_tod.get_parser, argv)
    finally:
        os.chdir(here)
        for executor in made:
            if executor is not None and hasattr(executor, "shutdown"):
                executor.shutdown(wait=True)


if __name__ == "__main__":
    main(sys.argv[1:])
