"""shadow_filter: tracked features and camera poses in, static/dynamic feature tracks out.

The Shadow filter of paper 001 (sec. II-III): every new feature is held back and tracked by
its own EKF, given the camera pose from outside (MonoSLAM, or ground truth), until a
chi-square test on its viewing rays calls it STATIC (handed over to SLAM on
shadow/static_features and forgotten here) or DYNAMIC (kept and tracked as it moves). The
algorithm is ``core.shadow_filter.ShadowFilter``; the stamp pairing, the pose covariance
check and the counts are ``shadow_processor.ShadowProcessor``'s; this node converts the
messages, hands them to it, publishes the processed frames and logs what it reports.

Topics:
  subscribes  features (slam_interfaces/FeatureTrackArray, reliable, depth 100): track ids
              and raw (distorted) pixels of one image, header.stamp = the image stamp
              (taken serialized and read from the CDR bytes: conversions.features_from_cdr).
              <pose_topic> (default monoslam/pose; geometry_msgs/PoseWithCovarianceStamped,
              reliable, depth 100): the pose of the camera OPTICAL frame (x right, y down,
              z forward) in the world frame header.frame_id, i.e. R_world_camera and the
              optical centre, at the image stamp. Covariance in ROS order (x, y, z, rotation
              about the world X, Y, Z axes), passed to the core unchanged (see conversions);
              all zero = a known pose. Every frame with a pose is processed, however
              uncertain the pose: its covariance widens the rays, so decisions come later.
              A frame whose pose covariance is not finite is skipped (a warning, counted).
              <pose_topic>/link (slam_interfaces/PoseLink, reliable, depth 100), optional:
              the pose error's covariances with the source's earlier poses; with them the
              all-view test models the drift the poses share (pose_link_messages).
              camera/camera_info (sensor_msgs/CameraInfo, best effort, depth 100 as it is taken
              in step with features): intrinsics and plumb_bob/rational_polynomial distortion;
              a change is applied from the next frame on and logged.
              monoslam/revoked (slam_interfaces/ShadowTrackArray, reliable, depth 100):
              features handed over earlier that SLAM then found moving. Each comes back as a
              suspect: tracked again from its next sighting, PENDING, with fresh views only,
              and handed over again only if STATIC with every direction of motion checked.
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
              /diagnostics (diagnostic_msgs/DiagnosticArray, every second): inputs received
              and dropped, frames processed, refused and skipped, classifications,
              processing time, lag (slam_ros.diagnostics)
  Every other output has header.stamp = the image stamp and header.frame_id = the pose's
  frame.

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
The poses come in stamp order, after the features by SLAM's processing time, which can be
longer than the horizon while SLAM lags: a features frame waits for its pose until a pose
with a later stamp has come (SLAM skipped the frame: it is dropped then), however late, up
to queue_size frames. Before the first pose, and for a frame that came after a later pose,
a frame whose pose has not come once the newest stamp seen is sync_horizon_s past it is
dropped. A frame still waiting when no input came for sync_horizon_s of wall time is
dropped, as is a pose no features frame paired with within the horizon; each drop is logged
once with its stamp. Each queue holds at most queue_size entries (the oldest goes first).
While no camera_info or no pose at all has come yet, the drops are summarized in a line
every few seconds instead.

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
  static_test                     the test of the static hypothesis: both (either rejecting
                                  is DYNAMIC), three_ray (the paper's) or all_view.
  pixel_sigma_px                  pixel noise per coordinate, px.
  tracking_offset_px, tracking_offset_time_s  the tracker's offsets that persist between
                                  images (px per coordinate; 0: white noise) and their
                                  correlation time (s), modelled in the static tests
                                  and kept per feature in its EKF state.
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
  sync_horizon_s (1.0)            how long a pose waits for its frame, and a frame for its
                                  pose before the first pose, s (stamp time; see above).
  queue_size (300)                waiting feature frames and poses, each (10 s at 30 Hz:
                                  how far SLAM's poses may lag before frames are dropped).
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

from geometry_msgs.msg import Point, PoseWithCovarianceStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from monoslam_shadow_node.conversions import (
    STATIC_MARKER_LIMIT,
    CameraInfoWatch,
    FloatArray,
    MarkerTypes,
    TrackFields,
    features_from_cdr,
    features_from_message,
    fill_markers,
    fill_track_array,
    handover_fields,
    pose_from_message,
    revoked_from_message,
    track_array_cdr,
)
from monoslam_shadow_node.core.shadow_filter import FrameResult, ShadowFilter
from monoslam_shadow_node.frame_sync import FrameSynchronizer
from monoslam_shadow_node.notices import LogThrottle, Notice, log_notice
from monoslam_shadow_node.pose_link_messages import LINK_SUFFIX, PoseLinks, link_from_message
from monoslam_shadow_node.settings import NODE_NAME, PARAMETERS, node_settings, shadow_config
from monoslam_shadow_node.shadow_processor import Outcome, ShadowProcessor, ShadowStep
from slam_core.cli import console_main
from slam_interfaces.msg import FeatureTrackArray, PoseLink, ShadowTrack, ShadowTrackArray
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.qos import output_qos, sensor_qos
from slam_ros.spin import spin_node

FEATURES_TOPIC = 'features'
CAMERA_INFO_TOPIC = 'camera/camera_info'
TRACKS_TOPIC = 'shadow/tracks'
STATIC_TOPIC = 'shadow/static_features'
MARKERS_TOPIC = 'shadow/markers'
REVOKED_TOPIC = 'monoslam/revoked'
INPUT_DEPTH = 100
STATUS_PERIOD_S = 10.0
WAITING_LOG_PERIOD_S = 5.0


def _deserialize_features(data: bytes) -> FeatureTrackArray:
    return deserialize_message(data, FeatureTrackArray)


class ShadowFilterNode(Node):
    """Thin adapter around ShadowProcessor: features and poses in, the tracks published."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        values = declare_parameters(self, PARAMETERS)
        self.config = shadow_config(values)
        self.settings = node_settings(values)
        self.processor = ShadowProcessor(
            self.config,
            stamp_tolerance_ns=self.settings.stamp_tolerance_ns,
            sync_horizon_ns=self.settings.sync_horizon_ns,
            queue_size=self.settings.queue_size,
            pose_topic=self.settings.pose_topic,
            camera_info_topic=CAMERA_INFO_TOPIC,
        )
        self.omitted = 0
        self._camera_watch = CameraInfoWatch(CAMERA_INFO_TOPIC)
        self._throttle = LogThrottle(WAITING_LOG_PERIOD_S)
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
        self.diagnostics = Diagnostics(self, self._counts)
        timed = self.diagnostics.timed
        inputs, info_qos = output_qos(depth=INPUT_DEPTH), sensor_qos(depth=INPUT_DEPTH)
        # taken serialized: features_from_cdr reads the ids and pixels from the bytes
        self.create_subscription(
            FeatureTrackArray, FEATURES_TOPIC, timed(self._on_features, 'features'), inputs,
            raw=True,
        )  # fmt: skip
        self.create_subscription(
            PoseWithCovarianceStamped,
            self.settings.pose_topic,
            timed(self._on_pose, 'pose'),
            inputs,
        )
        self._links = PoseLinks()  # pose_link_messages: the drift the poses share
        self.create_subscription(
            PoseLink, self.settings.pose_topic + LINK_SUFFIX, timed(self._on_link, 'link'), inputs
        )
        self.create_subscription(
            CameraInfo, CAMERA_INFO_TOPIC, timed(self._on_camera_info, 'camera_info'), info_qos
        )
        self.create_subscription(
            ShadowTrackArray, REVOKED_TOPIC, timed(self._on_revoked, 'revoked'), inputs
        )
        self.create_timer(
            max(self.settings.sync_horizon_ns / 2e9, 0.05),
            timed(self._flush_when_idle),
            clock=Clock(clock_type=ClockType.STEADY_TIME),
        )
        self.get_logger().info(
            f'waiting for {FEATURES_TOPIC}, {self.settings.pose_topic} and {CAMERA_INFO_TOPIC}'
        )

    def diagnostics_counts(self) -> dict[str, int]:
        """The counts the node reports on /diagnostics (``_counts``)."""
        return self._counts()

    def _counts(self) -> dict[str, int]:
        """The counts on /diagnostics: frames processed, refused (pose covariance not
        finite) and skipped, inputs dropped by the pairing, features handed over as static
        and called dynamic, held pending, camera_info messages rejected, the poses that came
        with and without their link to earlier poses, and the links rejected (unreadable) or
        unused (no pose of their stamp came) (``pose_link_messages``)."""
        counts = self.processor.counts
        return {
            'processed': counts.processed,
            'pose refused': counts.pose_refused,
            'skipped': counts.skipped,
            'dropped': counts.dropped_total,
            'static': counts.static_total,
            'dynamic': counts.dynamic_total,
            'pending': counts.held_pending,
            'camera_info rejected': self._camera_watch.rejected,
            'poses linked': self._links.linked,
            'poses unlinked': self._links.unlinked,
            'links rejected': self._links.rejected,
            'links unused': self._links.unused,
        }

    @property
    def shadow(self) -> ShadowFilter | None:
        """The filter, None before the first usable camera_info."""
        return self.processor.shadow

    @property
    def sync(self) -> FrameSynchronizer:
        """The processor's pairing of features with poses."""
        return self.processor.sync

    # --- inputs -----------------------------------------------------------------------------

    def _on_camera_info(self, message: CameraInfo) -> None:
        update = self._camera_watch.update(message)
        if update is None:
            return
        if update.camera is None:
            self.get_logger().error(update.text, throttle_duration_sec=WAITING_LOG_PERIOD_S)
            return
        if update.first:
            self.get_logger().info(update.text)
        else:
            self.get_logger().warning(update.text)
        self._handle(self.processor.set_camera(update.camera))

    def _on_features(self, message: bytes | FeatureTrackArray) -> None:
        self._last_input = time.monotonic()
        try:
            features = (
                features_from_message(message)
                if isinstance(message, FeatureTrackArray)
                else features_from_cdr(message, _deserialize_features)
            )
        except ValueError as err:  # not what a publisher of the type sends: counted, dropped
            self._handle(self.processor.reject('undecodable', str(err)))
            return
        self._handle(self.processor.add_features(features))

    def _on_pose(self, message: PoseWithCovarianceStamped) -> None:
        self._last_input = time.monotonic()
        for pose in self._links.on_pose(pose_from_message(message)):
            self._handle(self.processor.add_pose(pose))

    def _on_link(self, message: PoseLink) -> None:
        self._last_input = time.monotonic()
        try:
            ready = self._links.on_link(link_from_message(message))
        except ValueError as err:
            self._links.rejected += 1
            self.get_logger().warning(
                f'{self.settings.pose_topic}{LINK_SUFFIX}: {err}; link rejected, its pose is '
                'taken as independent of the earlier ones'
            )
            return
        for pose in ready:
            self._handle(self.processor.add_pose(pose))

    def _on_revoked(self, message: ShadowTrackArray) -> None:
        ids = revoked_from_message(message)
        taken = self.processor.revoke(ids)
        self.get_logger().info(
            f'{REVOKED_TOPIC}: SLAM revoked {len(ids)} feature(s); {len(taken)} of them '
            f'({", ".join(map(str, taken)) or "none"}) are tracked again as suspects '
            f'(fresh views only, every direction of motion checked)'
        )

    def _flush_when_idle(self) -> None:
        idle_s = time.monotonic() - self._last_input
        if idle_s > self.settings.sync_horizon_ns / 1e9:
            for pose in self._links.flush():  # its link did not come
                self._handle(self.processor.add_pose(pose))
            if self.processor.waiting_features:
                self._handle(self.processor.flush())

    # --- outputs ----------------------------------------------------------------------------

    def _handle(self, outcomes: list[Outcome]) -> None:
        """Log the notices and publish the processed frames, in order."""
        for outcome in outcomes:
            if isinstance(outcome, Notice):
                self._log(outcome)
            elif isinstance(outcome, ShadowStep):
                self._publish(outcome.result, outcome.frame_id)
                self._report_status()

    def _log(self, notice: Notice) -> None:
        log_notice(self.get_logger(), notice, self._throttle, time.monotonic())

    def _publish(self, result: FrameResult, frame_id: str) -> None:
        serialized, left_out = track_array_cdr(result.tracks, result.stamp_ns, frame_id)
        self._left_out(left_out, result)
        self.tracks_publisher.publish(serialized)
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
        self._left_out([track_id for track_id, fields in items if fields is None], result)
        return [fields for _, fields in items if fields is not None]

    def _left_out(self, left_out: list[int], result: FrameResult) -> None:
        if left_out:
            self.omitted += len(left_out)
            self.get_logger().error(
                f'frame at stamp {result.stamp_ns} ns: features {left_out} left out of the '
                'output, their estimate is not finite (a Shadow filter fault)'
            )

    def _report_status(self) -> None:
        now = time.monotonic()
        if now - self._status_time < STATUS_PERIOD_S:
            return
        frames = self.processor.counts.processed
        rate = (frames - self._status_frames) / (now - self._status_time)
        self.get_logger().info(self.processor.status_line(rate))
        self._status_time, self._status_frames = now, frames

    def destroy_node(self) -> None:
        """Log the final summary, then destroy."""
        counts = self.processor.counts
        if counts.processed or counts.dropped_total or counts.skipped or counts.pose_refused:
            links = self._links
            self.get_logger().info(
                f'done: {self.processor.status_line()}; poses with their link {links.linked}, '
                f'without {links.unlinked + len(links.flush())}'
            )
        super().destroy_node()


@console_main(NODE_NAME)
def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C (the Jazzy shutdown pattern)."""
    return spin_node(NODE_NAME, ShadowFilterNode, argv, parameters=PARAMETERS, doc=__doc__)


if __name__ == '__main__':
    sys.exit(main())
