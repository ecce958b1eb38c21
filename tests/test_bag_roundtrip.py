"""Topic-level: bag_player publishes a bag into real rclpy subscribers, bag_recorder records it.

The bag holds Image, CompressedImage, CameraInfo, Odometry, TFMessage and every
slam_interfaces message, with seeded random content. Equality is checked on the CDR bytes
(re-serialized from the deserialized rclpy messages), so every field and stamp is compared.
"""

from __future__ import annotations

import re
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bag_fixtures import all_test_topics, by_topic, decoded, read_back, tool_env
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosbags.typesys.store import Typestore

from slam_ros.testing.harness import RosHarness
from slam_ros.testing.messages import BagTopic, write_bag
from slam_ros.typesys import TypeRegistry, message_class

pytestmark = pytest.mark.topic


def test_player_delivers_every_message_in_order(ros_harness: RosHarness, tmp_path: Path) -> None:
    topics = all_test_topics()
    written = write_bag(tmp_path / 'input', topics, duration_s=1.0, seed=1)
    expected = by_topic(written)
    collectors = {t.name: ros_harness.collect(t.name, message_class(t.msgtype)) for t in topics}

    player = ros_harness.start_process(
        'player',
        ['bag_player', str(tmp_path / 'input'), '--wait-for-subscribers', '20'],
        env=tool_env(),
    )

    received = {
        topic: [serialize_message(m) for m in collector.wait_for_count(len(expected[topic]))]
        for topic, collector in collectors.items()
    }
    assert decoded(topics, received) == decoded(topics, expected)
    assert player.process.wait(timeout=30) == 0, player.log()
    assert sum(len(c) for c in collectors.values()) == len(written)


def test_recorder_round_trip_keeps_count_stamps_and_content(
    ros_harness: RosHarness, tmp_path: Path
) -> None:
    topics = all_test_topics()
    written = write_bag(tmp_path / 'input', topics, duration_s=1.0, seed=2)
    recorder = ros_harness.start_process(
        'recorder',
        ['bag_recorder', *(t.name for t in topics), '-o', str(tmp_path / 'recorded')],
        env=tool_env(),
    )
    player = ros_harness.start_process(
        'player',
        ['bag_player', str(tmp_path / 'input'), '--wait-for-subscribers', '20'],
        env=tool_env(),
    )
    assert player.process.wait(timeout=60) == 0, player.log()
    # The player is done; the recorder has everything once its log reports nothing pending.
    assert recorder.stop() == 0, recorder.log()

    recorded = read_back(tmp_path / 'recorded')
    assert decoded(topics, recorded) == decoded(topics, by_topic(written))
    stamps = [m.timestamp_ns for m in written if m.topic == '/odom']
    store = TypeRegistry().typestore
    recorded_stamps = [
        (lambda s: s.sec * 10**9 + s.nanosec)(
            store.deserialize_cdr(data, 'nav_msgs/msg/Odometry').header.stamp
        )
        for data in recorded['/odom']
    ]
    assert recorded_stamps == stamps


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_recorder_killed_mid_run_keeps_everything_received(
    ros_harness: RosHarness, tmp_path: Path, signum: int
) -> None:
    topics = (
        BagTopic('/odom', 'nav_msgs/msg/Odometry', 50.0),
        BagTopic('/camera/image_raw', 'sensor_msgs/msg/Image', 10.0),
    )
    written = write_bag(tmp_path / 'input', topics, duration_s=6.0, seed=3)
    # Probe /clock, not a bag topic: the player must wait for the recorder's subscriptions.
    clock = ros_harness.collect(
        '/clock',
        message_class('rosgraph_msgs/msg/Clock'),
        QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT),
    )
    recorder = ros_harness.start_process(
        'recorder',
        [
            'bag_recorder',
            '-a',
            '--exclude',  # the bag's topics only: not the player's and its own /diagnostics
            '/clock',
            '/diagnostics',
            '/rosout',
            '/parameter_events',
            '-o',
            str(tmp_path / 'recorded'),
        ],
        env=tool_env(),
    )
    ros_harness.start_process(
        'player',
        ['bag_player', str(tmp_path / 'input'), '--wait-for-subscribers', '20'],
        env=tool_env(),
    )
    bag_start_s = written[0].timestamp_ns // 10**9
    clock.wait_for(lambda m: m.clock.sec >= bag_start_s + 2, timeout_s=30)  # 2 s into 6 s
    recorder.process.send_signal(signum)
    assert recorder.process.wait(timeout=20) == 0, recorder.log()

    recorded = read_back(tmp_path / 'recorded')
    expected = by_topic(written)
    total = sum(len(v) for v in recorded.values())
    assert 0 < total < len(written)
    for topic, messages in decoded(topics, recorded).items():
        # Everything received is there: a gap-free prefix of what was played.
        assert messages == decoded(topics, expected)[topic][: len(messages)], topic
    match = re.search(r'wrote (\d+) messages', recorder.log())
    assert match is not None and int(match.group(1)) == total


def test_player_replays_sqlite3_and_ros1_bags(ros_harness: RosHarness, tmp_path: Path) -> None:
    from rosbags.rosbag1 import Writer as Ros1Writer
    from rosbags.typesys import Stores, get_typestore

    written = write_bag(
        tmp_path / 'sqlite',
        (BagTopic('/odom', 'nav_msgs/msg/Odometry', 20.0),),
        duration_s=0.5,
        storage='sqlite3',
        seed=4,
    )
    ros1 = get_typestore(Stores.ROS1_NOETIC)
    header_cls = ros1.types['std_msgs/msg/Header']
    time_cls = ros1.types['builtin_interfaces/msg/Time']
    ros1_x = np.random.default_rng(5).normal(size=8)
    template = _zero_ros1_odometry(ros1)
    with Ros1Writer(tmp_path / 'legacy.bag') as writer:
        connection = writer.add_connection('/wheel_odom', 'nav_msgs/msg/Odometry', typestore=ros1)
        for i, x in enumerate(ros1_x):
            template.header = header_cls(
                seq=i, stamp=time_cls(sec=100 + i, nanosec=7), frame_id='odom'
            )
            template.pose.pose.position.x = float(x)
            writer.write(
                connection,
                (100 + i) * 10**9 + 7,
                bytes(ros1.serialize_ros1(template, 'nav_msgs/msg/Odometry')),
            )

    odometry = message_class('nav_msgs/msg/Odometry')
    from_sqlite = ros_harness.collect('/odom', odometry)
    from_ros1 = ros_harness.collect('/wheel_odom', odometry)
    for name, bag in (('sqlite', tmp_path / 'sqlite'), ('ros1', tmp_path / 'legacy.bag')):
        player = ros_harness.start_process(
            name,
            ['bag_player', str(bag), '--wait-for-subscribers', '20', '--rate', '5'],
            env=tool_env(),
        )
        assert player.process.wait(timeout=60) == 0, player.log()

    sqlite_topics = (BagTopic('/odom', 'nav_msgs/msg/Odometry', 20.0),)
    received = [serialize_message(m) for m in from_sqlite.wait_for_count(len(written))]
    assert decoded(sqlite_topics, {'/odom': received}) == decoded(sqlite_topics, by_topic(written))
    received = from_ros1.wait_for_count(len(ros1_x))
    assert [m.pose.pose.position.x for m in received] == list(ros1_x)
    assert [(m.header.stamp.sec, m.header.frame_id) for m in received] == [
        (100 + i, 'odom') for i in range(len(ros1_x))
    ]


def _zero_ros1_odometry(store: Typestore) -> Any:
    """A ROS 1 (with header seq) Odometry message of zeros."""
    types = store.types
    time_cls = types['builtin_interfaces/msg/Time']
    point = types['geometry_msgs/msg/Point'](x=0.0, y=0.0, z=0.0)
    quaternion = types['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)
    vector = types['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0)
    return types['nav_msgs/msg/Odometry'](
        header=types['std_msgs/msg/Header'](seq=0, stamp=time_cls(sec=0, nanosec=0), frame_id=''),
        child_frame_id='base_link',
        pose=types['geometry_msgs/msg/PoseWithCovariance'](
            pose=types['geometry_msgs/msg/Pose'](position=point, orientation=quaternion),
            covariance=np.zeros(36),
        ),
        twist=types['geometry_msgs/msg/TwistWithCovariance'](
            twist=types['geometry_msgs/msg/Twist'](linear=vector, angular=vector),
            covariance=np.zeros(36),
        ),
    )
