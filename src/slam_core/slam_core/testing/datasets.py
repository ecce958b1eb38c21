"""The real datasets in tests: the path of one, or the test skips and says where it looked."""

from __future__ import annotations

from pathlib import Path

import pytest

from slam_core.datasets import DATA_ENV, data_root, dataset


def dataset_or_skip(relative: str, name: str) -> Path:
    """Return ``data_root()/relative``, or skip the test saying where it looked."""
    path = dataset(relative)
    if path is None:
        pytest.skip(f'{name} not found at {data_root() / relative} (set {DATA_ENV})')
    return path
