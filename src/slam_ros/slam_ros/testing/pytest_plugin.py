"""pytest fixtures: isolated ROS_DOMAIN_ID, ``ros_harness`` (docs/design/ros_and_core.md)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

DOMAIN_ENV = 'SLAM_TEST_DOMAIN_ID'
# Fast DDS computes ports from the domain id; ids above 232 overflow the port range.
DOMAIN_RANGE = (101, 232)


def session_domain_id() -> int:
    """Return this session's isolated domain id."""
    if DOMAIN_ENV in os.environ:
        return int(os.environ[DOMAIN_ENV])
    low, high = DOMAIN_RANGE
    return low + os.getpid() % (high - low)


def pytest_configure(config: pytest.Config) -> None:
    os.environ['ROS_DOMAIN_ID'] = str(session_domain_id())
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('RCUTILS_LOGGING_BUFFERED_STREAM', '0')


def pytest_report_header(config: pytest.Config) -> str:
    return (
        f'ROS_DOMAIN_ID={os.environ.get("ROS_DOMAIN_ID")} '
        f'discovery={os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")} '
        f'dds-profile={os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE", "none")}'
    )


@pytest.fixture(scope='session')
def ros_context() -> Iterator[None]:
    """Initialize rclpy once for the session (in the isolated domain)."""
    import rclpy

    if not rclpy.ok():
        rclpy.init()
    yield
    rclpy.try_shutdown()


@pytest.fixture
def ros_harness(ros_context: None, tmp_path: Path) -> Iterator[object]:
    """A fresh RosHarness per test; logs of subprocess nodes go to tmp_path."""
    from slam_ros.testing.harness import RosHarness

    harness = RosHarness(tmp_path)
    try:
        yield harness
    finally:
        harness.close()
