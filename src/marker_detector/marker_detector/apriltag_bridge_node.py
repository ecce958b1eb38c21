"""apriltag_bridge: apriltag_ros detections in, marker_detector's landmark observations out.

For a robot that already runs apriltag_ros (github.com/christianrauch/apriltag_ros, the ROS 2
AprilTag node): each AprilTagDetectionArray it publishes, with the tag poses it sends on /tf
(camera frame -> ``<family>:<id>``, stamped with the image) and the camera mount on
/tf_static, becomes a LandmarkObservationArray exactly as marker_detector publishes it:
range and bearing of each tag's centre in the base frame, the covariance from the same
sensor model (corner noise pixel_noise_px through the corner Jacobian at the tag's pose,
then into range and bearing), the same quality gates, the image's stamp. odometry_ingest
and em_sam_mapper take it unchanged. The conversion is marker_detector.apriltag_bridge.

apriltag_ros publishes the detections first and the transforms right after, from the same
image callback, so a detection waits for its tags' transforms: up to tf_wait_s of wall time
(0.5 s: the two arrive milliseconds apart, and a longer wait only delays every observation
behind a missing one, since they leave in order), given up only at the second 0.1 s check
after that, so that transforms queued while the node was busy are taken first. A tag whose
transform did not come (apriltag_ros without pose estimation, a renamed frame), or without a
camera_info or camera mount by then, is dropped, counted and logged with the reason; a tag
of another family is counted and logged; an id outside allowed_ids is counted.

Topics:
  subscribes  detections (apriltag_msgs/AprilTagDetectionArray, reliable, depth 100;
              apriltag_ros publishes reliable)
              /tf (tf2_msgs/TFMessage, reliable, depth 100): the tag poses (other frames
              are ignored)
              /tf_static (tf2_msgs/TFMessage, transient local): the camera mount
              camera/camera_info (sensor_msgs/CameraInfo, best effort): the camera model
  publishes   landmark_observations (slam_interfaces/LandmarkObservationArray, base frame,
              only for detections with at least one accepted tag; reliable, transient-local
              (a restarted mapper gets them again), depth 1000)
              /diagnostics (diagnostic_msgs/DiagnosticArray, every second): detections
              received and lost, processed, tags dropped by reason, other family, id not
              allowed, rejected by the gates, observations, pending (slam_ros.diagnostics)

Parameters (all read-only):
  tag_family ('tag36h11')     the family in the detections: tag16h5, tag25h9, tag36h11,
                              tagCircle21h7, tagCircle49h12, tagCustom48h12,
                              tagStandard41h12, tagStandard52h13 (apriltag_ros's family
                              parameter with 'tag' in front).
  marker_size_m (0.16)        side of every tag's black square, m (apriltag_ros's size).
  marker_sizes_m ([])         per-id sizes, entries 'id:size_m' (its tag.ids + tag.sizes).
  allowed_ids ([])            only these ids, entries 'id' or 'first-last'; empty: all.
  tag_frames ([])             tag frame names, entries 'id:frame' (its tag.ids + tag.frames);
                              others are '<tag_family>:<id>'.
  camera_model ('rectified')  'rectified': apriltag_ros detects in image_rect, the pinhole
                              camera_info P (as it does); 'raw': in the raw image, K and D.
  min_side_px (12.0), max_reprojection_error_px (2.0), max_range_m (8.0),
  max_viewing_angle_rad (1.22)  marker_detector's gates; the reprojection error is that of
                              the tag's corners at its pose from /tf (a tag size or camera
                              model that differs from apriltag_ros's shows there).
  pixel_noise_px (0.5)        corner noise sigma behind the covariance, px.
  base_frame ('base_link')    frame of the observations; the mount comes from /tf_static.
  tf_wait_s (0.5)             how long a detection waits for its transforms, s (wall time).

Run next to apriltag_ros:
  ros2 run apriltag_ros apriltag_node --ros-args -r image_rect:=/camera/image_rect \\
      -r camera_info:=/camera/camera_info -p family:=36h11 -p size:=0.16
  ros2 run marker_detector apriltag_bridge --ros-args \\
      --params-file config/apriltag_bridge.yaml -p marker_size_m:=0.16
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np
from apriltag_msgs.msg import AprilTagDetectionArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo
from tf2_msgs.msg import TFMessage

from marker_detector.apriltag_bridge import AprilTagBridge, BridgeOutput, Tag
from marker_detector.apriltag_settings import PARAMETERS, bridge_config
from marker_detector.conversions import camera_info_fields, fill_observations, transform_matrix
from marker_detector.processor import InputError
from slam_core.cli import console_main
from slam_core.stamps import stamp_to_ns
from slam_interfaces.msg import LandmarkObservation, LandmarkObservationArray
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.qos import latched_qos, output_qos, replayed_qos, sensor_qos
from slam_ros.spin import spin_node

CHECK_PERIOD_S = 0.1
"""How often waiting detections are checked against tf_wait_s."""


def tags_from_message(message: Any) -> list[Tag]:
    """The tags of an AprilTagDetectionArray (fields read by name)."""
    return [
        Tag(
            family=str(item.family),
            id=int(item.id),
            corners_px=np.array([[c.x, c.y] for c in item.corners], dtype=np.float64),
        )
        for item in message.detections
    ]


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
            if output.frame.observations:
                message = LandmarkObservationArray()
                fill_observations(output.frame, message, LandmarkObservation)
                self.observations_publisher.publish(message)

    def _counts(self) -> dict[str, int]:
        """The counts on /diagnostics: detection arrays processed, tags dropped (and why),
        of another family, with an id not allowed, rejected by the gates; observations
        published; camera_info messages and transforms rejected; detection arrays waiting."""
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
