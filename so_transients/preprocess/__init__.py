"""The transient steps as sotodlib preprocess processes: thin wrappers around the core.

- :mod:`.processes`: ``transient_jumps``, ``transient_pca_mask``, ``transient_filter``,
  ``transient_find``, ``transient_cuts``, ``transient_significance``, ``transient_fit``
  (registered on import)
- :mod:`.sotodlib_steps`: sotodlib's ``fourier_filter``, ``glitches`` and ``pca_filter`` a
  chunk at a time (``transient_fourier_filter``, ``transient_glitches``,
  ``transient_pca_filter``)
- :mod:`.step_fields`: the AxisManager fields each step reads
- :mod:`.slot_storage`: candidate tables stored on the detector axis of the archive
- :mod:`.plots`: one figure per detection

The only subpackage that knows sotodlib's ``_Preprocess``; nothing below it imports it.
Importing the subpackage registers every step with sotodlib's ``Pipeline`` (the package does
so as soon as ``sotodlib.preprocess`` is imported).
"""
from so_transients.preprocess import processes  # noqa: F401  the transient_* steps
from so_transients.preprocess import sotodlib_steps  # noqa: F401  the chunked standard ones
