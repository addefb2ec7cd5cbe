"""so_transients: rapid-transient search in SO LAT time-ordered data.

Importing the package registers its sotodlib extensions: the preprocess steps
(``transient_filter``, ``transient_find``, ``transient_cuts``, ``transient_significance``,
``transient_fit``, ... and the chunked standard ones) with sotodlib's ``Pipeline``, and the
``so_transients`` obs loader for simulated datasets. Each is registered as soon as the sotodlib
module it extends is imported (at once when it already is: :mod:`.common.post_import`), so that
importing the package alone stays quick. List ``so_transients`` under ``imports:`` in a
context.yaml so that sotodlib (and the site pipeline's spawned workers) import it.
"""
from importlib.metadata import version

from so_transients.common.post_import import when_imported

__version__ = version(__name__)   # pyproject.toml holds the one version number


def _register_steps():
    import importlib

    importlib.import_module("so_transients.preprocess")   # registers every step


def _register_loader():
    from so_transients.io.loader import register

    register()


when_imported("sotodlib.preprocess", _register_steps)
when_imported("sotodlib.core", _register_loader)
