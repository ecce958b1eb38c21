"""Topic-level: odometry_ingest and em_sam_mapper on their own and on the office bag
(``em_sam_office``) online, and their parameters refused by name (real rclpy); the offline
map's outputs are read in test_em_sam_map_topics."""

from __future__ import annotations

import math
import time

import pytest
import rclpy
from bag_fixtures import invalid_parameter_error
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from std_msgs.msg import Empty
from tf2_msgs.msg import TFMessage

from em_sam_node.odometry_ingest.node import OdometryIngestNode
from slam_core.stamps import ns_to_stamp, stamp_to_ns
from slam_ros.progress import END_QOS, END_TOPIC
from slam_ros.qos import sensor_qos
from slam_ros.testing.harness import RosHarness, wait_until

pytestmark = pytest.mark.topic


@pytest.mark.parametrize(
    ('executable', 'parameter', 'value'),
    [
        ('em_sam_mapper', 'lagrange_lambda', '0.0'),
        ('em_sam_mapper', 'lagrange_lambda', '-5.0'),
        ('em_sam_mapper', 'mode', 'fancy'),
        ('odometry_ingest', 'keyframe_distance_m', '-1.0'),
        ('odometry_ingest', 'noise_alphas', '[0.1, 0.2]'),
    ],
)
def test_invalid_parameter_is_named(executable: str, parameter: str, value: str) -> None:
    error = invalid_parameter_error([executable], parameter, value)
    assert parameter in error


def test_odometry_ingest_publishes_odom_to_base_link_when_asked(ros_harness: RosHarness) -> None:
    """publish_tf: each odometry sample's pose on /tf as odom -> base_link at its stamp (what
    a base driver publishes); a NaN pose or a stamp not after the last one is not published,
    and is counted and logged."""
    tf = ros_harness.collect('/tf', TFMessage)
    ingest = ros_harness.add_node(
        OdometryIngestNode(parameter_overrides=[Parameter('publish_tf', value=True)])
    )
    odom = ros_harness.publisher('odom', Odometry, sensor_qos())
    ros_harness.wait_for_subscribers(odom)

    def sample(stamp_ns: int, x: float) -> Odometry:
        message = Odometry()
        ns_to_stamp(stamp_ns, message.header.stamp)
        message.header.frame_id, message.child_frame_id = 'odom', 'base_link'
        message.pose.pose.position.x = x
        message.pose.pose.orientation.w = 1.0
        return message

    for stamp_ns, x in ((1_000, 0.1), (2_000, math.nan), (2_000, 0.2), (1_500, 0.3), (3_000, 0.4)):
        odom.publish(sample(stamp_ns, x))
        time.sleep(0.05)  # best effort, one at a time
    wait_until(lambda: ingest.tf_published + ingest.tf_skipped == 5, what='5 samples taken')
    wait_until(lambda: sum(len(m.transforms) for m in tf.messages) == 3, what='3 transforms')
    transforms = [t for m in tf.messages for t in m.transforms]
    assert [(t.header.frame_id, t.child_frame_id) for t in transforms] == [
        ('odom', 'base_link')
    ] * 3
    assert [stamp_to_ns(t.header.stamp) for t in transforms] == [1_000, 2_000, 3_000]
    assert [t.transform.translation.x for t in transforms] == [0.1, 0.2, 0.4]
    assert ingest.tf_skipped == 2


def test_odometry_ingest_does_not_flush_when_its_process_only_stalled(ros_context: None) -> None:
    """After a stall of its process, the idle timer runs before the odometry that queued
    meanwhile: one idle tick arms the flush, the queued sample disarms it, and only idle
    seen on two ticks in a row flushes (a mid-run flush adds a keyframe at the last sample;
    CI, test_mapper_respawn_topics: 1803 keyframes against 1802). The node is not spun: the
    test calls its timer callback as the executor would."""
    ingest = OdometryIngestNode()
    flushes: list[int] = []
    ingest.ingest.flush = lambda: flushes.append(1) or []  # type: ignore[method-assign]
    try:
        sample = Odometry()
        sample.pose.pose.orientation.w = 1.0
        for stamp_ns in (1_000_000, 2_000_000):
            ns_to_stamp(stamp_ns, sample.header.stamp)
            ingest._on_odometry(sample)
        stalled = time.monotonic() - 2 * ingest.idle_flush_s
        ingest._last_odometry_wall = stalled
        ingest._flush_when_idle()  # the timer first, after the stall
        ns_to_stamp(3_000_000, sample.header.stamp)
        ingest._on_odometry(sample)  # then the sample that queued meanwhile
        ingest._flush_when_idle()
        assert flushes == []
        ingest._last_odometry_wall = stalled  # really idle: two ticks in a row
        ingest._flush_when_idle()
        assert flushes == []
        ingest._flush_when_idle()
        assert flushes == [1]
        ingest._flush_when_idle()  # once
        assert flushes == [1]
    finally:
        ingest.destroy_node()


def test_odometry_ingest_waits_for_a_running_players_end_of_input(ros_context: None) -> None:
    """While a bag_player that says the end of its bag runs, a pause of the odometry is not
    its end (a busy machine paused the player: CI, test_mapper_respawn_topics, 1803 keyframes
    against 1802); the player's /slam/end_of_input flushes. Once no such player runs, idle
    odometry flushes again, and odometry after an idle flush is counted. Not spun: the test
    calls the callbacks as the executor would (count_publishers reads the DDS graph)."""
    ingest = OdometryIngestNode()
    player = rclpy.create_node('end_of_input_speaker')
    flushes: list[int] = []
    flush = ingest.ingest.flush
    ingest.ingest.flush = lambda: flushes.append(1) or flush()  # type: ignore[method-assign]
    warnings: list[str] = []
    ingest.get_logger().warning = lambda text, **_: warnings.append(text)  # type: ignore[method-assign]
    sample = Odometry()
    sample.pose.pose.orientation.w = 1.0

    def odometry(stamp_ns: int) -> None:
        ns_to_stamp(stamp_ns, sample.header.stamp)
        ingest._on_odometry(sample)

    try:
        end = player.create_publisher(Empty, END_TOPIC, END_QOS)
        wait_until(
            lambda: ingest.count_publishers(END_TOPIC) > 0, timeout_s=10, what='the speaker'
        )
        odometry(1_000_000)
        odometry(500_000_000)
        ingest._last_odometry_wall = time.monotonic() - 10 * ingest.idle_flush_s
        for _ in range(4):
            ingest._flush_when_idle()
        assert flushes == []
        ingest._on_end(Empty())
        assert flushes == [1] and ingest.published == 1  # the held-back keyframe, said
        odometry(900_000_000)
        odometry(1_300_000_000)
        player.destroy_publisher(end)
        wait_until(
            lambda: ingest.count_publishers(END_TOPIC) == 0, timeout_s=10, what='no speaker'
        )
        ingest._last_odometry_wall = time.monotonic() - 10 * ingest.idle_flush_s
        ingest._flush_when_idle()
        ingest._flush_when_idle()
        assert flushes == [1, 1] and ingest.published == 2
        assert ingest.idle_flushes == 1 and warnings == []
        odometry(1_700_000_000)  # after an idle flush that emitted: warned, counted
        assert ingest._counts()['idle flushes'] == 1
        assert len(warnings) == 1 and 'odometry resumed after a pause' in warnings[0]
    finally:
        player.destroy_node()
        ingest.destroy_node()
