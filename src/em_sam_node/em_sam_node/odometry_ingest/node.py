"""odometry_ingest: wheel odometry in, keyframe-to-keyframe OdometryIncrement out.

Makes a keyframe at every observation stamp (odometry interpolated there) and at motion
thresholds; an empty observation array makes none, but says how far a lagging detector has
got, and keyframes wait for it. Each increment carries the paper's eq. 2 motion (forward,
side, angular) and a covariance that grows with the motion. Odometry resets, out-of-order
stamps and NaN poses are dropped with a throttled warning. Held-back keyframes are emitted
when a bag_player says its bag ended (/slam/end_of_input), or live when odometry stops for
``idle_flush_s``.

Topics:
  subscribes  odom (nav_msgs/Odometry, best effort, 1000), landmark_observations (stamps
              only, reliable, 1000), /slam/end_of_input (std_msgs/Empty, transient-local)
  publishes   odometry_increments (OdometryIncrement, reliable, 1000, transient-local),
              /tf (odom_frame -> base_frame, with publish_tf), /diagnostics
Frames: increments are motion of base_frame, expressed in odom_frame poses.
Parameters: ``odometry_ingest --help``. In full: docs/design/em_sam_nodes.md.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import Empty
from tf2_msgs.msg import TFMessage

from em_sam_node.core.inputs import Increment
from em_sam_node.odometry_ingest.conversions import increment_to_message, odometry_pose
from em_sam_node.odometry_ingest.processor import OdometryIngest
from em_sam_node.odometry_ingest.settings import PARAMETERS, config_from_parameters
from slam_core.cli import console_main
from slam_core.stamps import stamp_to_ns
from slam_interfaces.msg import LandmarkObservationArray, OdometryIncrement
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.progress import END_QOS, END_TOPIC, paced
from slam_ros.qos import output_qos, replayed_qos, sensor_qos
from slam_ros.spin import spin_node


def odometry_transform(message: Any, odom_frame: str, base_frame: str) -> Any:
    """Return the TransformStamped odom_frame -> base_frame of a nav_msgs/Odometry, or None
    when its pose is not finite."""
    pose = message.pose.pose
    p, q = pose.position, pose.orientation
    values = [p.x, p.y, p.z, q.x, q.y, q.z, q.w]
    if not all(math.isfinite(v) for v in values) or not any(values[3:]):
        return None
    transform = TransformStamped()
    transform.header.stamp = message.header.stamp
    transform.header.frame_id = odom_frame
    transform.child_frame_id = base_frame
    transform.transform.translation.x = p.x
    transform.transform.translation.y = p.y
    transform.transform.translation.z = p.z
    transform.transform.rotation = q
    return transform


class OdometryIngestNode(Node):
    """Thin adapter around OdometryIngest."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('odometry_ingest', **kwargs)
        values = declare_parameters(self, PARAMETERS)
        self.ingest = OdometryIngest(config_from_parameters(values), warn=self._warn)
        self.idle_flush_s = float(values['idle_flush_s'])
        self.base_frame = str(values['base_frame'])
        self.odom_frame = str(values['odom_frame'])
        self.publisher = self.create_publisher(
            OdometryIncrement, 'odometry_increments', replayed_qos(depth=1000)
        )
        self.tf_publisher = (
            self.create_publisher(TFMessage, '/tf', output_qos(depth=100))
            if values['publish_tf']
            else None
        )
        self.tf_published = 0
        self.tf_skipped = 0
        self._last_tf_ns: int | None = None
        self.published = 0
        self._hold_logged = False
        self.diagnostics = Diagnostics(self, self._counts)
        timed = self.diagnostics.timed
        self.create_subscription(
            Odometry, 'odom', timed(self._on_odometry, 'odom'), sensor_qos(depth=1000)
        )
        self.create_subscription(
            LandmarkObservationArray,
            'landmark_observations',
            timed(self._on_observations, 'landmark_observations'),
            replayed_qos(1000) if values['observations_transient_local'] else output_qos(1000),
        )
        self._last_odometry_wall = time.monotonic()
        self.flushed = True
        self.idle_flushes = 0  # flushes on idle odometry (not said by a player)
        self._idle_flush_emitted = False  # the last flush was on idle and emitted keyframes
        self._idle_armed = False
        # the end of the inputs is said by the player when there is one (slam_ros.progress)
        self.create_subscription(Empty, END_TOPIC, timed(self._on_end, 'end'), END_QOS)
        if not paced():
            self.create_timer(
                self.idle_flush_s / 2.0,
                timed(self._flush_when_idle),
                clock=Clock(clock_type=ClockType.STEADY_TIME),
            )

    def _counts(self) -> dict[str, int]:
        """The counts on /diagnostics (increments, drops, resets, TF)."""
        return {
            'increments': self.published,
            'dropped': self.ingest.dropped_samples,
            'observation stamps refused': self.ingest.refused_stamps,
            'resets': self.ingest.resets,
            'tf published': self.tf_published,
            'tf skipped': self.tf_skipped,
            'idle flushes': self.idle_flushes,
        }

    def _warn(self, message: str) -> None:
        self.get_logger().warning(message, throttle_duration_sec=2.0)

    def _on_odometry(self, message: Odometry) -> None:
        stamp_ns, pose = odometry_pose(message)
        self._last_odometry_wall = time.monotonic()
        if self._idle_flush_emitted:
            self.get_logger().warning(
                f'odometry resumed after a pause of more than idle_flush_s='
                f'{self.idle_flush_s:g} s, taken for its end: the held-back keyframes were '
                f'flushed, so this run has a keyframe that an unpaused stream does not '
                f'({self.idle_flushes} such flush(es) so far)'
            )
        self.flushed, self._idle_flush_emitted = False, False
        self._publish(self.ingest.add_odometry(stamp_ns, pose))
        if self.tf_publisher is not None:
            self._publish_tf(self.tf_publisher, message, stamp_ns)

    def _publish_tf(self, publisher: Any, message: Odometry, stamp_ns: int) -> None:
        transform = odometry_transform(message, self.odom_frame, self.base_frame)
        if transform is None or (self._last_tf_ns is not None and stamp_ns <= self._last_tf_ns):
            self.tf_skipped += 1
            self._warn(
                f'odometry at {stamp_ns} ns: not on /tf (pose not finite, or stamp not after '
                f'the last one); {self.tf_skipped} skipped so far'
            )
            return
        publisher.publish(TFMessage(transforms=[transform]))
        self._last_tf_ns = stamp_ns
        self.tf_published += 1

    def _on_observations(self, message: LandmarkObservationArray) -> None:
        stamp_ns = stamp_to_ns(message.header.stamp)
        self._publish(self.ingest.add_observation_stamp(stamp_ns, seen=bool(message.observations)))

    def _flush_when_idle(self) -> None:
        """Flush once the odometry has been idle on two ticks in a row (no bag player running)."""
        idle = time.monotonic() - self._last_odometry_wall > self.idle_flush_s
        # a player that says the end of its bag is running: a pause is not the end
        player = self.count_publishers(END_TOPIC) > 0
        if self.flushed or not idle or player:
            self._idle_armed = False
            return
        if not self._idle_armed:
            self._idle_armed = True
            return
        self.flushed = True
        self.idle_flushes += 1
        increments = self.ingest.flush()
        self._idle_flush_emitted = bool(increments)
        self._publish(increments)

    def _on_end(self, message: Empty) -> None:
        self.flushed = True
        self._publish(self.ingest.flush())

    def _publish(self, increments: list[Increment]) -> None:
        if self.ingest.hold_ended and not self._hold_logged:
            self._hold_logged = True
            self.get_logger().info(f'startup hold of keyframes ended {self.ingest.hold_ended}')
        for increment in increments:
            self.publisher.publish(
                increment_to_message(
                    increment,
                    OdometryIncrement(),
                    base_frame=self.base_frame,
                    odom_frame=self.odom_frame,
                )
            )
            self.published += 1


@console_main('odometry_ingest')
def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C (the Jazzy shutdown pattern)."""
    return spin_node(
        'odometry_ingest', OdometryIngestNode, argv, parameters=PARAMETERS, doc=__doc__
    )


if __name__ == '__main__':
    sys.exit(main())
