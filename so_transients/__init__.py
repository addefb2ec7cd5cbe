"""so_transients: rapid-transient search in SO LAT time-ordered data.

Importing the package registers its sotodlib extensions: the preprocess steps
``transient_filter``, ``transient_find``, ``transient_cuts``, ``transient_significance`` and
``transient_fit``, and the
``so_transients`` obs loader for simulated datasets. List ``so_transients`` under ``imports:``
in a context.yaml so that sotodlib (and the site pipeline's spawned workers) import it.
"""
from importlib.metadata import version

from so_transients.preprocess import processes  # noqa: F401  registers the transient_* preprocess steps
from so_transients.preprocess import sotodlib_steps  # noqa: F401  and the chunked standard ones
from so_transients.io.loader import register as _register_loader

__version__ = version(__name__)   # pyproject.toml holds the one version number

_register_loader()
