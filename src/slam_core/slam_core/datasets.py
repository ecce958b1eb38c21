"""Where the real datasets live: ``$SLAM_DATA_DIR``, else ``<repo>/../shared/data``."""

from __future__ import annotations

import os
from pathlib import Path

DATA_ENV = 'SLAM_DATA_DIR'


def repo_root() -> Path:
    """Return the repository root (``$SLAM_REPO_ROOT`` from scripts/env.sh, else the cwd)."""
    return Path(os.environ.get('SLAM_REPO_ROOT', Path.cwd())).resolve()


def data_root() -> Path:
    """Return the datasets directory; it may not exist (callers skip or explain)."""
    if DATA_ENV in os.environ:
        return Path(os.environ[DATA_ENV]).expanduser().resolve()
    return (repo_root().parent / 'shared' / 'data').resolve()


def dataset(relative: str) -> Path | None:
    """Return ``data_root()/relative`` if it exists, else None."""
    path = data_root() / relative
    return path if path.exists() else None
