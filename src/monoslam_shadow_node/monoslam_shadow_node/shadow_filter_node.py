"""shadow_filter: tracked features and camera poses in, static/dynamic feature tracks out.

The Shadow filter of paper 001 (sec. II-III): every new feature is held back and tracked by
its own EKF, given the camera pose from outside (MonoSLAM, or ground truth), until a
chi-square test on its viewing rays calls it STATIC (handed over to SLAM on
shadow/static_features and forgotten here) or DYNAMIC (kept and tracked as it moves). The
algorithm is ``core.shadow_filter.ShadowFilter``; this node pairs each FeatureTrackArray with
the camera pose of the same stamp, feeds the frames in stamp order and publishes the result.

Topics:
  subscribes  features (slam_interfaces/FeatureTrackArray, reliable, depth 100): track ids
              and raw (distorted) pixels of one image, header.stamp = the image stamp.
              <pose_topic> (default monoslam/pose; geometry_msgs/PoseWithCovarianceStamped,
              reliable, depth 100): the pose of the camera OPTICAL frame (x right, y down,
              z forward) in the world frame header.frame_id, i.e. R_world_camera and the
              optical centre, at the image stamp. Covariance in ROS order (x, y, z, rotation
              about the world X, Y, Z axes), passed to the core unchanged (see conversions);
              all zero = a known pose.
              camera/camera_info (sensor_msgs/CameraInfo, best effort): intrinsics and
              plumb_bob/rational_polynomial distortion; a change is applied from the next
              frame on and logged.
  publishes   shadow/tracks (slam_interfaces/ShadowTrackArray, reliable, depth 10), every
              processed frame: every feature the filter holds that was seen in it, PENDING
              or DYNAMIC, and STATIC in the frame it is handed over; world position and
              velocity with covariances (row-major 3x3).
              shadow/static_features (slam_interfaces/ShadowTrackArray, reliable, depth 100),
              only for frames with handovers: status STATIC, the position triangulated from
              all views as a static point with its covariance, zero velocity with zero
              covariance, the deciding test's statistic. Each feature appears once.
              shadow/markers (visualization_msgs/MarkerArray, reliable, depth 5), when
              publish_markers is true and someone subscribes: pending features red, dynamic
              green, handed-over static features blue (the latest 5000), trajectories of
              dynamic features as green line strips (as the paper's Fig. 4).
  Every output has header.stamp = the image stamp and header.frame_id = the pose's frame.

No NaN is ever published (details in conversions):
  - position not yet defined (depth unknown: inverse depth not 3 sigma above zero): position
    is a point on the viewing ray 1000 m away, position_covariance = [-1, 0, ..., 0]
    (sensor_msgs "no estimate" convention);
  - no test yet: test_statistic = -1.0 and test_dof = 0 (T >= 0 otherwise);
  - any other non-finite number (a core fault) is replaced by "no estimate", or the track is
    left out, with an error in the log.

Synchronization: features and poses pair when their stamps differ by at most
stamp_tolerance_s (default 0: equal stamps), nearest first. Frames are processed in stamp
order as soon as paired; a frame that still waits for its pose holds back the later ones.
A features frame whose pose has not come once the newest stamp seen is sync_horizon_s past
it (or no input came for sync_horizon_s of wall time) is dropped, as is a pose no features
frame paired with within the horizon; each drop is logged once with its stamp. Each queue
holds at most queue_size entries (the oldest goes first). While no camera_info or no pose at
all has come yet, the drops are summarized in a line every few seconds instead.

Bad input is logged with its culprit and the node goes on: features before any camera_info
(held and processed once it arrives), a pose or features frame without partner (dropped as
above), a frame out of stamp order, a pose with NaN or a non-rotation, NaN pixels (those
features are ignored), repeated ids, an unusable camera_info.

Parameters (Shadow filter): the fields of the core's ClassifierConfig, EkfConfig and
ShadowConfig, one to one; their defaults are the core's, written out in
config/shadow_filter.yaml (a test keeps the two equal).
  alpha                           probability of calling a static feature dynamic.
  min_parallax_deg, parallax_growth  test j waits for a parallax of
                                  min_parallax_deg * parallax_growth**j, deg.
  max_tests                       tests per feature; after them it stays PENDING.
  min_baseline_m                  camera travel since first sight before any test, m.
  middle_min_fraction             the middle view lies at least this share of the baseline
                                  from both ends.
  min_detectable_speed_m_s, detection_power, unchecked_directions  STATIC only once this
                                  speed (m/s) would have been seen with this power in all but
                                  the unchecked_directions least visible directions of motion
                                  (0 m/s: any accepted test decides).
  pixel_sigma_px                  pixel noise per coordinate, px.
  initial_inverse_depth_per_m, initial_inverse_depth_sigma_per_m  the inverse depth (1/m) a
                                  new feature starts at, and its standard deviation.
  velocity_sigma_m_s              prior velocity standard deviation of a new feature, m/s.
  acceleration_psd_m2_s3          white acceleration noise density, m^2/s^3.
  camera_translation_sigma_m, camera_rotation_sigma_rad  camera motion noise per frame added
                                  in the prediction, m and rad.
  innovation_gate_probability     chi-square gate of the measurement updates.
  max_missed_frames               a feature unseen this many frames is forgotten.
  trajectory_length               positions kept per feature for its trajectory (0: none).
  classify                        false: a tracker only; every feature stays PENDING.
Parameters (node):
  pose_topic ('monoslam/pose')    camera pose topic.
  stamp_tolerance_s (0.0)         largest features-to-pose stamp difference, s.
  sync_horizon_s (1.0)            how long a frame waits for its partner, s (stamp time).
  queue_size (100)                waiting feature frames and poses, each.
  max_pose_position_sigma_m (.inf), max_pose_rotation_sigma_rad (.inf)  the pose gate: a
                                  frame whose pose has a position standard deviation above
                                  the first (m) or a rotation one above the second (rad)
                                  (sqrt of the covariance diagonal, the largest of the three
                                  each) is skipped, not given to the filter, debug-logged
                                  and counted in the status line. Paper 001's Shadow filter
                                  relies on SLAM's pose; a poor one (just after a start or a
                                  long occlusion) makes static features look like moving
                                  ones. .inf (the default): no gate; the MonoSLAM pipeline
                                  uses 0.03 m and 0.01 rad (monoslam_pipeline's
                                  DEFAULT_SHADOW_MAX_POSE_SIGMA). A known pose (all-zero
                                  covariance) always passes.
  publish_markers (true)          publish shadow/markers.
All are read-only; a bad value stops the node with an error naming the parameter.

Frames: the world frame is the pose's header.frame_id (e.g. map); features are in the
camera optical frame of the camera_info.
"""

from __future__ import annotations

import sys
import time
from collections import OrderedDict
from typing import Any

import numpy as np
from geometry_msgs.msg import Point, PoseWithCovarianceStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from monoslam_shadow_node.conversions import (
    STATIC_MARKER_LIMIT,
    CameraInfoWatch,
    CameraPose,
    Features,
    FloatArray,
    MarkerTypes,
    TrackFields,
    features_from_message,
    fill_markers,
    fill_track_array,
    frame_input,
    handover_fields,
    pose_from_message,
    track_fields,
)
from monoslam_shadow_node.core.shadow_filter import (
    DYNAMIC,
    PENDING,
    FrameResult,
    InputError,
    ShadowFilter,
)
from monoslam_shadow_node.frame_sync import Drop, FrameSynchronizer
from monoslam_shadow_node.settings import NODE_NAME, PARAMETERS, node_settings, shadow_config
from slam_core.cli import console_main
from slam_interfaces.msg import FeatureTrackArray, ShadowTrack, ShadowTrackArray
from slam_ros.params import declare_parameters
from slam_ros.qos import output_qos, sensor_qos
from slam_ros.spin import spin_node

FEATURES_TOPIC = 'features'
CAMERA_INFO_TOPIC = 'camera/camera_info'
TRACKS_TOPIC = 'shadow/tracks'
STATIC_TOPIC = 'shadow/static_features'
MARKERS_TOPIC = 'shadow/markers'
INPUT_DEPTH = 100
STATUS_PERIOD_S = 10.0
WAITING_LOG_PERIOD_S = 5.0
# The core's warnings are text: bad input (NaN pixels) is logged as a warning, the rest
# (gated measurements, filter restarts, tests put off) is filter life, logged at debug level
# and counted in the status line.
INPUT_WARNING = 'non-finite'
GATE_WARNING = 'outside the innovation gate'


def pose_gate_excess(covariance: FloatArray | None, max_sigma: tuple[float, float]) -> str | None:
    """Return why a pose covariance (6, 6) (position m, rotation rad) fails the pose gate
    (position, rotation) standard deviations, or None when it passes. A known pose (None) and
    a covariance that is not finite (the core rejects it with its reason) pass."""
    if covariance is None:
        return None
    variances = np.diagonal(covariance)
    if not np.all(np.isfinite(variances)):
        return None
    sigma = np.sqrt(np.maximum(variances, 0.0))
    position, rotation = float(sigma[:3].max()), float(sigma[3:].max())
    if position > max_sigma[0]:
        return f'position sigma {position:.3g} m > max_pose_position_sigma_m ({max_sigma[0]:g})'
    if rotation > max_sigma[1]:
        return (
            f'rotation sigma {rotation:.3g} rad > max_pose_rotation_sigma_rad ({max_sigma[1]:g})'
        )
    return None


class ShadowFilterNode(Node):
    """Thin adapter around ShadowFilter: pairs features with poses, publishes the tracks."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        values = declare_parameters(self, PARAMETERS)
        self.config = shadow_config(values)
        self.settings = node_settings(values)
        self.shadow: ShadowFilter | None = None
        self._camera_watch = CameraInfoWatch(CAMERA_INFO_TOPIC)
        self.sync = FrameSynchronizer(
            tolerance_ns=self.settings.stamp_tolerance_ns,
            horizon_ns=self.settings.sync_horizon_ns,
            max_entries=self.settings.queue_size,
            pose_topic=self.settings.pose_topic,
        )
        self.frames = self.skipped = self.dropped = self.gated = self.pose_gated = 0
        self._poses_seen = self._dropped_waiting = 0
        self.static_total = self.dynamic_total = self.omitted = 0
        self._held = {PENDING: 0, DYNAMIC: 0}
        self._static_positions: OrderedDict[int, FloatArray] = OrderedDict()
        self._marker_types = MarkerTypes(Marker, Point, ColorRGBA)
        self._last_input = time.monotonic()
        self._status_time, self._status_frames = time.monotonic(), 0
        self.tracks_publisher = self.create_publisher(ShadowTrackArray, TRACKS_TOPIC, output_qos())
        self.static_publisher = self.create_publisher(
            ShadowTrackArray, STATIC_TOPIC, output_qos(depth=100)
        )
        self.markers_publisher = (
            self.create_publisher(MarkerArray, MARKERS_TOPIC, output_qos(depth=5))
            if self.settings.publish_markers
            else None
        )
        self.create_subscription(
            FeatureTrackArray, FEATURES_TOPIC, self._on_features, output_qos(depth=INPUT_DEPTH)
        )
        self.create_subscription(
            PoseWithCovarianceStamped,
            self.settings.pose_topic,
            self._on_pose,
            output_qos(depth=INPUT_DEPTH),
        )
        self.create_subscription(CameraInfo, CAMERA_INFO_TOPIC, self._on_camera_info, sensor_qos())
        self.create_timer(
            max(self.settings.sync_horizon_ns / 2e9, 0.05),
            self._flush_when_idle,
            clock=Clock(clock_type=ClockType.STEADY_TIME),
        )
        self.get_logger().info(
            f'waiting for {FEATURES_TOPIC}, {self.settings.pose_topic} and {CAMERA_INFO_TOPIC}'
        )

    # --- inputs -----------------------------------------------------------------------------

    def _on_camera_info(self, message: CameraInfo) -> None:
        update = self._camera_watch.update(message)
        if update is None:
            return
        if update.camera is None:
            self.get_logger().error(update.text, throttle_duration_sec=WAITING_LOG_PERIOD_S)
            return
        if self.shadow is None:
            self.shadow = ShadowFilter(update.camera, self.config)
            self.get_logger().info(update.text)
        else:
            self.shadow.set_camera(update.camera)
            self.get_logger().warning(update.text)
        self._drain()

    def _on_features(self, message: FeatureTrackArray) -> None:
        self._last_input = time.monotonic()
        self._report_drops(self.sync.add_features(features_from_message(message)))
        if self.shadow is None:
            dropped = f', {self._dropped_waiting} dropped' if self._dropped_waiting else ''
            self.get_logger().warning(
                f'no {CAMERA_INFO_TOPIC} received yet: holding {self.sync.waiting_features} '
                f'feature frame(s) until it comes{dropped}',
                throttle_duration_sec=WAITING_LOG_PERIOD_S,
            )
        self._drain()

    def _on_pose(self, message: PoseWithCovarianceStamped) -> None:
        self._last_input = time.monotonic()
        self._poses_seen += 1
        self._report_drops(self.sync.add_pose(pose_from_message(message)))
        self._drain()

    def _flush_when_idle(self) -> None:
        idle_s = time.monotonic() - self._last_input
        if self.sync.waiting_features and idle_s > self.settings.sync_horizon_ns / 1e9:
            self._drain(flush=True)

    # --- processing -------------------------------------------------------------------------

    def _drain(self, *, flush: bool = False) -> None:
        pairs, drops = self.sync.pop(hold=self.shadow is None, flush=flush)
        self._report_drops(drops)
        for features, pose in pairs:
            self._process(features, pose)

    def _report_drops(self, drops: list[Drop]) -> None:
        """Log every drop once; a steady state (no camera_info or no pose at all yet, which
        drops every frame) is summarized in throttled lines instead."""
        for drop in drops:
            self.dropped += 1
            if self.shadow is None and drop.kind == 'overflow':
                self._dropped_waiting += 1  # said in the throttled "no camera_info" line
            elif drop.kind == 'no_pose' and not self._poses_seen:
                self.get_logger().warning(
                    f'no camera pose received on {self.settings.pose_topic} at all yet: '
                    f'dropping feature frames ({self.dropped} dropped so far, the latest at '
                    f'stamp {drop.stamp_ns} ns); is it published, and remapped?',
                    throttle_duration_sec=WAITING_LOG_PERIOD_S,
                )
            else:
                self.get_logger().warning(drop.text)

    def _process(self, features: Features, pose: CameraPose) -> None:
        if self.shadow is None:  # cannot happen: pop(hold=True) pairs nothing before a camera
            return
        excess = pose_gate_excess(pose.covariance, self.settings.max_pose_sigma)
        if excess is not None:
            self.pose_gated += 1
            self.get_logger().debug(
                f'frame at stamp {features.stamp_ns} ns skipped by the pose gate: {excess}'
            )
            return
        try:
            result = self.shadow.process(frame_input(features, pose))
        except InputError as err:
            self.skipped += 1
            self.get_logger().error(f'frame at stamp {features.stamp_ns} ns skipped: {err}')
            return
        self.frames += 1
        for warning in result.warnings:
            if INPUT_WARNING in warning:
                self.get_logger().warning(f'frame at stamp {result.stamp_ns} ns: {warning}')
                continue
            self.gated += GATE_WARNING in warning
            self.get_logger().debug(f'frame at stamp {result.stamp_ns} ns: {warning}')
        self._count(result)
        self._publish(result, pose.frame_id)
        self._report_status()

    def _count(self, result: FrameResult) -> None:
        self._held = {
            status: sum(t.status == status for t in result.tracks) for status in (PENDING, DYNAMIC)
        }
        self.static_total += len(result.handovers)
        self.dynamic_total += sum(d.status == DYNAMIC for d in result.decisions)

    def _publish(self, result: FrameResult, frame_id: str) -> None:
        tracks = self._finite([(t.id, track_fields(t)) for t in result.tracks], result)
        self.tracks_publisher.publish(
            fill_track_array(tracks, result.stamp_ns, frame_id, ShadowTrackArray(), ShadowTrack)
        )
        if result.handovers:
            tests = {t.id: (t.test_statistic, t.test_dof) for t in result.tracks}
            handed = self._finite(
                [
                    (h.id, handover_fields(h, *tests.get(h.id, (float('nan'), 0))))
                    for h in result.handovers
                ],
                result,
            )
            self.static_publisher.publish(
                fill_track_array(
                    handed, result.stamp_ns, frame_id, ShadowTrackArray(), ShadowTrack
                )
            )
            for handover in result.handovers:
                self._static_positions[handover.id] = handover.position
            while len(self._static_positions) > STATIC_MARKER_LIMIT:
                self._static_positions.popitem(last=False)
        publisher = self.markers_publisher
        if publisher is not None and publisher.get_subscription_count():
            publisher.publish(
                fill_markers(
                    result.tracks, self._static_positions.values(), result.stamp_ns, frame_id,
                    MarkerArray(), self._marker_types,
                )
            )  # fmt: skip

    def _finite(
        self, items: list[tuple[int, TrackFields | None]], result: FrameResult
    ) -> list[TrackFields]:
        left_out = [track_id for track_id, fields in items if fields is None]
        if left_out:
            self.omitted += len(left_out)
            self.get_logger().error(
                f'frame at stamp {result.stamp_ns} ns: features {left_out} left out of the '
                'output, their estimate is not finite (a Shadow filter fault)'
            )
        return [fields for _, fields in items if fields is not None]

    def _report_status(self) -> None:
        now = time.monotonic()
        if now - self._status_time < STATUS_PERIOD_S:
            return
        rate = (self.frames - self._status_frames) / (now - self._status_time)
        self.get_logger().info(self.status_line(rate))
        self._status_time, self._status_frames = now, self.frames

    def status_line(self, rate_hz: float | None = None) -> str:
        """Return the progress summary: frames, held features, decisions, problems."""
        rate = f' ({rate_hz:.1f}/s)' if rate_hz is not None else ''
        return (
            f'{self.frames} frames{rate}: holding {self._held[PENDING]} pending and '
            f'{self._held[DYNAMIC]} dynamic features; {self.static_total} handed over as '
            f'static, {self.dynamic_total} called dynamic so far; {self.skipped} frames '
            f'skipped, {self.pose_gated} over the pose gate, {self.dropped} inputs dropped, '
            f'{self.gated} measurements outside the innovation gate'
        )

    def destroy_node(self) -> None:
        """Log the final summary, then destroy."""
        if self.frames or self.dropped or self.skipped or self.pose_gated:
            self.get_logger().info(f'done: {self.status_line()}')
        super().destroy_node()


@console_main(NODE_NAME)
def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C (the Jazzy shutdown pattern)."""
    return spin_node(NODE_NAME, ShadowFilterNode, argv, parameters=PARAMETERS, doc=__doc__)


if __name__ == '__main__':
    sys.exit(main())
