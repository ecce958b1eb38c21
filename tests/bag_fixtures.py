"""Shared helpers for the bag tool tests: topic sets and reading a bag back."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

from slam_ros.bag.source import BagSource
from slam_ros.testing.messages import BagTopic, WrittenMessage, decode_all
from slam_ros.typesys import TypeRegistry, find_msg_file

STANDARD_TOPICS = (
    BagTopic('/camera/image_raw', 'sensor_msgs/msg/Image', 10.0),
    BagTopic('/camera/image_raw/compressed', 'sensor_msgs/msg/CompressedImage', 10.0),
    BagTopic('/camera/camera_info', 'sensor_msgs/msg/CameraInfo', 10.0),
    BagTopic('/odom', 'nav_msgs/msg/Odometry', 20.0),
    BagTopic('/tf', 'tf2_msgs/msg/TFMessage', 20.0),
)


def slam_interface_types() -> list[str]:
    """Every message type slam_interfaces installs (found through AMENT_PREFIX_PATH)."""
    probe = find_msg_file('slam_interfaces/msg/LandmarkMap')
    if probe is None:
        raise RuntimeError('slam_interfaces is not installed; run scripts/bootstrap.sh')
    return sorted(f'slam_interfaces/msg/{p.stem}' for p in probe.parent.glob('*.msg'))


def snake_case(name: str) -> str:
    """LandmarkMap -> landmark_map."""
    return re.sub(r'(?<!^)(?=[A-Z])', '_', name).lower()


def all_test_topics() -> tuple[BagTopic, ...]:
    """Standard sensor topics plus one topic per slam_interfaces message."""
    ours = tuple(
        BagTopic(f'/slam/{snake_case(t.rsplit("/", 1)[1])}', t, 5.0)
        for t in slam_interface_types()
    )
    return STANDARD_TOPICS + ours


def by_topic(messages: list[WrittenMessage]) -> dict[str, list[bytes]]:
    """Group written messages' CDR bytes by topic, keeping order."""
    grouped: dict[str, list[bytes]] = {}
    for message in messages:
        grouped.setdefault(message.topic, []).append(message.data)
    return grouped


def read_back(path: Path) -> dict[str, list[bytes]]:
    """Read a bag and group its CDR bytes by topic in stamp order."""
    grouped: dict[str, list[bytes]] = {}
    with BagSource(path) as source:
        for message in source.messages():
            grouped.setdefault(message.topic, []).append(message.data)
    return grouped


def tool_env() -> dict[str, str]:
    """Environment for tool subprocesses: unbuffered, no colour codes in logs."""
    return {**os.environ, 'PYTHONUNBUFFERED': '1', 'RCUTILS_COLORIZED_OUTPUT': '0'}


def invalid_parameter_error(command: list[str], parameter: str, value: str) -> str:
    """Start a node (``command``) with ``parameter`` set to the bad ``value``; assert that it
    exits with status 2, without a traceback and with exactly one error line; return it."""
    result = subprocess.run(
        [*command, '--ros-args', '-p', f'{parameter}:={value}'],
        capture_output=True,
        text=True,
        timeout=60,
        env=tool_env(),
        check=False,
    )
    assert result.returncode == 2, result.stderr
    assert 'Traceback' not in result.stderr
    errors = [line for line in result.stderr.splitlines() if ': error: ' in line]
    assert len(errors) == 1, result.stderr
    return errors[0]


def decoded(topics: tuple[BagTopic, ...], payloads: dict[str, list[bytes]]) -> dict[str, list]:
    """Decode CDR payloads per topic into plain structures (see testing.messages.plain)."""
    registry = TypeRegistry()
    types = {t.name: t.msgtype for t in topics}
    return {name: decode_all(registry, types[name], data) for name, data in payloads.items()}
