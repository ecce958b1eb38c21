"""Workspace-wide pytest configuration: the topic-level test harness, and the order files
run in."""

from __future__ import annotations

import pytest

pytest_plugins = ['slam_ros.testing.pytest_plugin']


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Files holding a ``slow`` test first, in collection order otherwise: with the suite's
    ``--dist loadfile --no-loadscope-reorder`` (scripts/test.sh) the longest files start
    first instead of finishing alone at the end."""
    slow = {item.path for item in items if item.get_closest_marker('slow') is not None}
    items.sort(key=lambda item: item.path not in slow)
