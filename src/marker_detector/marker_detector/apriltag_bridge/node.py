"""apriltag_bridge: apriltag_ros detections in, marker_detector's landmark observations out.

For a robot that already runs apriltag_ros: each AprilTagDetectionArray, with the tag poses on
/tf and the camera mount on /tf_static, becomes a LandmarkObservationArray as marker_detector
publishes it (same sensor model, gates and stamp). A detection waits up to tf_wait_s for its
tags' transforms; a tag without one, or of another family or id, is dropped and counted.

Topics:
  subscribes  detections (apriltag_msgs/AprilTagDetectionArray, reliable, 100), /tf (the tag
              poses), /tf_static (the camera mount), camera/camera_info
  publishes   landmark_observations (LandmarkObservationArray, base frame, one per detection
              array, empty when nothing passed, reliable, transient-local, 1000), /diagnostics
All parameters are read-only. Next to apriltag_ros, in full: docs/design/marker_nodes.md
"""

from __future__ import annotations

import sys
import time
from typing import Any

from apriltag_msgs.msg import AprilTagDetectionArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo
from tf2_msgs.msg import TFMessage

from marker_detector.apriltag_bridge.conversions import tags_from_message
from marker_detector.apriltag_bridge.processor import AprilTagBridge, BridgeOutput
from marker_detector.apriltag_bridge.settings import PARAMETERS, bridge_config
from marker_detector.common.conversions import (
    camera_info_fields,
    fill_observations,
    transform_matrix,
)
from marker_detector.core.frame_types import InputError
from slam_core.cli import console_main
from slam_core.stamps import stamp_to_ns
from slam_interfaces.msg import LandmarkObservation, LandmarkObservationArray
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.qos import latched_qos, output_qos, replayed_qos, sensor_qos
from slam_ros.spin import spin_node

CHECK_PERIOD_S = 0.1
"""How often waiting detections are checked against tf_wait_s."""


class AprilTagBridgeNode(Node):
    """Thin adapter around AprilTagBridge."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('apriltag_bridge', **kwargs)
        self.bridge = AprilTagBridge(bridge_config(declare_parameters(self, PARAMETERS)))
        self.diagnostics = Diagnostics(self, self._counts)
        timed = self.diagnostics.timed
        self.observations_publisher = self.create_publisher(
            LandmarkObservationArray, 'landmark_observations', replayed_qos(depth=1000)
        )
        self.create_subscription(
            AprilTagDetectionArray,
            'detections',
            timed(self._on_detections, 'detections'),
            output_qos(depth=100),
        )
        self.create_subscription(TFMessage, '/tf', timed(self._on_tf, 'tf'), output_qos(100))
        self.create_subscription(
            TFMessage, '/tf_static', timed(self._on_tf_static, 'tf_static'), latched_qos(100)
        )
        self.create_subscription(
            CameraInfo, 'camera/camera_info', timed(self._on_camera_info, 'camera_info'),
            sensor_qos(),
        )  # fmt: skip
        self.create_timer(
            CHECK_PERIOD_S, timed(self._check), clock=Clock(clock_type=ClockType.STEADY_TIME)
        )

    def _error(self, message: str) -> None:
        self.get_logger().error(message, throttle_duration_sec=2.0)

    def _on_camera_info(self, message: CameraInfo) -> None:
        try:
            self.bridge.set_camera_info(**camera_info_fields(message), p=list(message.p))
        except InputError as err:
            self._error(str(err))
            return
        self._publish(self.bridge.poll(time.monotonic()))

    def _on_tf_static(self, message: TFMessage) -> None:
        for transform in message.transforms:
            try:
                self.bridge.static.add(
                    transform.header.frame_id,
                    transform.child_frame_id,
                    transform_matrix(transform.transform),
                )
            except InputError as err:
                self.bridge.counts['tf_static rejected'] += 1
                self._error(f'/tf_static: {err}')
        self._publish(self.bridge.poll(time.monotonic()))

    def _on_tf(self, message: TFMessage) -> None:
        for transform in message.transforms:
            if not self.bridge.config.is_tag_frame(transform.child_frame_id.lstrip('/')):
                continue
            try:
                matrix = transform_matrix(transform.transform)
            except InputError as err:
                self.bridge.counts['tf rejected'] += 1
                self._error(f'/tf {transform.child_frame_id!r}: {err}')
                continue
            self.bridge.add_transform(
                transform.header.frame_id,
                transform.child_frame_id,
                stamp_to_ns(transform.header.stamp),
                matrix,
            )
        self._publish(self.bridge.poll(time.monotonic()))

    def _on_detections(self, message: AprilTagDetectionArray) -> None:
        now = time.monotonic()
        warnings = self.bridge.add_detections(
            stamp_to_ns(message.header.stamp), message.header.frame_id,
            tags_from_message(message), now,
        )  # fmt: skip
        for warning in warnings:
            self.get_logger().warning(warning, throttle_duration_sec=2.0)
        self._publish(self.bridge.poll(now))

    def _check(self) -> None:
        self._publish(self.bridge.poll(time.monotonic(), expire=True))

    def _publish(self, outputs: list[BridgeOutput]) -> None:
        for output in outputs:
            for lost in output.lost:
                self._error(f'{lost.message} ({self.bridge.counts["dropped"]} dropped so far)')
            # empty too: it tells odometry_ingest how far the bridge has got
            message = LandmarkObservationArray()
            fill_observations(output.frame, message, LandmarkObservation)
            self.observations_publisher.publish(message)

    def _counts(self) -> dict[str, int]:
        """The counts on /diagnostics (the LOST_* reasons among them) and the arrays waiting."""
        counts = {
            key: 0
            for key in (
                'processed', 'dropped', 'dropped no tag tf', 'dropped no camera_info',
                'dropped no camera mount', 'dropped queue full', 'other family',
                'id not allowed', 'rejected', 'observations', 'camera_info rejected',
                'tf rejected', 'tf_static rejected',
            )
        }  # fmt: skip
        counts.update(self.bridge.counts)
        counts['pending'] = len(self.bridge.pending)
        return counts


@console_main('apriltag_bridge')
def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C (the Jazzy shutdown pattern)."""
    return spin_node(
        'apriltag_bridge', AprilTagBridgeNode, argv, parameters=PARAMETERS, doc=__doc__
    )


if __name__ == '__main__':
    sys.exit(main())
