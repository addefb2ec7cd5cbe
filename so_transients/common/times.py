"""Times as users give them and as tables show them: ctime seconds and ISO UTC."""
from __future__ import annotations

import numpy as np
from astropy.time import Time


def parse_time(value) -> float:
    """A ctime from ctime seconds (a number) or an ISO UTC string (``2023-11-14T22:14:32``)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        pass
    try:
        return float(Time(str(value), scale="utc").unix)
    except ValueError:
        raise ValueError(f"{value!r}: not a ctime nor an ISO UTC time") from None


def utc(ctime) -> np.ndarray:
    """ISO UTC strings of ctimes (seconds)."""
    ctime = np.atleast_1d(np.asarray(ctime, np.float64))
    return Time(ctime, format="unix").isot if len(ctime) else np.zeros(0, "U23")
