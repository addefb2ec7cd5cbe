"""Credentials never leave the process: a URL's password hidden wherever it is written to a
table or an alert, or logged."""
from __future__ import annotations

import re

_PASSWORD = re.compile(r"(?P<head>://[^/@:]*:)[^@/]*@")


def redacted(spec) -> str:
    """``spec`` with any password of a URL in it (``scheme://user:password@host``) as
    ``***``; anything else unchanged."""
    return _PASSWORD.sub(r"\g<head>***@", str(spec))
