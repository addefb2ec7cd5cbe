"""Code that runs once a module is imported: at once when it already is, else right after its
import completes (a finder placed first on ``sys.meta_path`` that wraps the module's loader).

The package registers its sotodlib extensions this way, so that ``import so_transients`` (a
context's ``imports:``, the command line's ``--help``) does not itself import sotodlib's
preprocess module and its ``tod_ops`` (several seconds).
"""
from __future__ import annotations

import importlib.abc
import importlib.util
import sys


class _AfterImport(importlib.abc.MetaPathFinder):
    """Finds ``name`` through the other finders and runs ``callback`` after its loader."""

    def __init__(self, name, callback):
        self.name, self.callback = name, callback

    def find_spec(self, fullname, path=None, target=None):
        if fullname != self.name:
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(fullname)
        if spec is None or spec.loader is None:
            return spec
        exec_module, callback = spec.loader.exec_module, self.callback

        def exec_then_call(module):
            exec_module(module)
            callback()

        spec.loader.exec_module = exec_then_call
        return spec


def when_imported(name: str, callback):
    """Call ``callback()`` once module ``name`` is imported (now, if it is)."""
    if name in sys.modules:
        callback()
    else:
        sys.meta_path.insert(0, _AfterImport(name, callback))
