"""Topic-level: bag_player's start offset, topic selection, remapping, loop and /clock."""

from __future__ import annotations

from pathlib import Path

import pytest
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy

from slam_bringup.bag_player import BagPlayerNode
from slam_ros.testing.harness import RosHarness
from slam_ros.testing.messages import BagTopic, write_bag
from slam_ros.typesys import message_class

pytestmark = pytest.mark.topic

TOPICS = (
    BagTopic('/odom', 'nav_msgs/msg/Odometry', 20.0),
    BagTopic('/camera/camera_info', 'sensor_msgs/msg/CameraInfo', 10.0),
)
ODOMETRY = message_class('nav_msgs/msg/Odometry')


def stamp_ns(message: object) -> int:
    stamp = message.header.stamp  # type: ignore[attr-defined]
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


def start_player(harness: RosHarness, **parameters: object) -> BagPlayerNode:
    overrides = [Parameter(name, value=value) for name, value in parameters.items()]
    overrides.append(Parameter('wait_for_subscribers_s', value=20.0))
    return harness.add_node(BagPlayerNode(parameter_overrides=overrides))  # type: ignore[return-value]


def test_start_offset_selection_and_remap(ros_harness: RosHarness, tmp_path: Path) -> None:
    written = write_bag(tmp_path / 'bag', TOPICS, duration_s=2.0, seed=21)
    start = written[0].timestamp_ns
    expected = [
        m.timestamp_ns
        for m in written
        if m.topic == '/odom' and m.timestamp_ns >= start + 5 * 10**8
    ]
    remapped = ros_harness.collect('/robot/odom', ODOMETRY)
    unselected = ros_harness.collect(
        '/camera/camera_info', message_class('sensor_msgs/msg/CameraInfo')
    )

    player = start_player(
        ros_harness,
        bag_path=str(tmp_path / 'bag'),
        start_offset_s=0.5,
        topics=['/odom'],
        remap=['/odom:=/robot/odom'],
        rate=4.0,
    )
    assert player.finished.wait(30) and player.error is None
    assert [stamp_ns(m) for m in remapped.wait_for_count(len(expected))] == expected
    assert len(unselected) == 0


def test_loop_replays_the_bag_again(ros_harness: RosHarness, tmp_path: Path) -> None:
    written = write_bag(tmp_path / 'bag', TOPICS[:1], duration_s=0.5, seed=22)
    stamps = [m.timestamp_ns for m in written]
    odom = ros_harness.collect('/odom', ODOMETRY)
    player = start_player(ros_harness, bag_path=str(tmp_path / 'bag'), loop=True, rate=5.0)
    received = odom.wait_for_count(2 * len(stamps) + 1)
    player.stop()
    assert [stamp_ns(m) for m in received[: 2 * len(stamps)]] == stamps + stamps
    assert player.error is None


def test_clock_follows_bag_time(ros_harness: RosHarness, tmp_path: Path) -> None:
    written = write_bag(tmp_path / 'bag', TOPICS[:1], duration_s=1.0, seed=23)
    clock = ros_harness.collect(
        '/clock',
        message_class('rosgraph_msgs/msg/Clock'),
        QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT),
    )
    ros_harness.collect('/odom', ODOMETRY)
    player = start_player(ros_harness, bag_path=str(tmp_path / 'bag'), clock_hz=50.0)
    assert player.finished.wait(30) and player.error is None
    times = [m.clock.sec * 10**9 + m.clock.nanosec for m in clock.wait_for_count(20)]
    assert times == sorted(times)
    assert written[0].timestamp_ns <= times[0] and times[-1] <= written[-1].timestamp_ns
    # 50 Hz over about 1 s of bag time: ticks about 20 ms apart.
    assert 15 * 10**6 < (times[-1] - times[0]) / (len(times) - 1) < 30 * 10**6
