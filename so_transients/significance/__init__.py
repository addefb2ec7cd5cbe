"""A false-alarm rate for every candidate (``transient_significance``), on arrays.

- :mod:`.far`: the step's core: each scan's map, its time slides and sign-inverted data,
  and ``far`` per candidate
- :mod:`.slide_groups`: detectors slid in groups so that slides share their sums
- :mod:`.slide_maxima`: a slide map's high local maxima, found coarse to fine
- :mod:`.stack_slides`: time slides of sweep stacks
- :mod:`.joint_far`: the joint-band statistic's background and ``far``
- :mod:`.tail_model`: counting beyond the measured background with a tail model

Imports from :mod:`so_transients.common`, :mod:`so_transients.detect` and
:mod:`so_transients.coherent`.
"""
