"""Where a study's table came from: the commit of the code that measured it and the day."""
from __future__ import annotations

import os
import subprocess
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def commit() -> str:
    """The short hash of the checkout the package runs from ('' outside a git checkout);
    ``+dirty`` when it has uncommitted changes to tracked files."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                              capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=ROOT, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return ""
    return head + ("+dirty" if dirty.strip() else "")


def today() -> str:
    """Today's UTC date, YYYY-MM-DD."""
    return datetime.now(timezone.utc).strftime("%Y-%m-%d")


def stamp(made_at=None) -> str:
    """``commit <hash>, <YYYY-MM-DD>``: what a study's table records of the code and the day
    that made it (``made_at``: the commit, this checkout's by default)."""
    return f"commit {made_at or commit()}, {today()}"


def repository_path(path, parts=1) -> str:
    """``path`` relative to the repository when it lies inside it, else its last ``parts``
    components alone: a table that records where its inputs came from never names a folder
    outside the repository."""
    path = Path(os.path.abspath(path))       # as named: a symlink into the package is kept
    try:
        return str(path.relative_to(ROOT))
    except ValueError:
        return str(Path(*path.parts[-parts:]))
