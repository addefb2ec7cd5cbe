"""Times as users give them: ctime seconds or ISO UTC."""
from __future__ import annotations

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
