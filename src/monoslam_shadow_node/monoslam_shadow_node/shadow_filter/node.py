"""shadow_filter: tracked features and camera poses in, static/dynamic feature tracks out.

The Shadow filter of paper 001: every new feature is tracked by its own EKF, given the camera
pose from outside, until a chi-square test calls it STATIC (handed over to SLAM) or DYNAMIC
(kept and tracked). Features and poses pair by stamp and are processed in stamp order;
nothing published is ever NaN; bad input is logged with its culprit and skipped.

Topics:
  subscribes  features (FeatureTrackArray), <pose_topic> (PoseWithCovarianceStamped, default
              monoslam/pose) and <pose_topic>/link (PoseLink, optional), camera/camera_info,
              monoslam/revoked (ShadowTrackArray: handovers SLAM found moving)
  publishes   shadow/tracks, shadow/static_features (ShadowTrackArray), shadow/markers
              (MarkerArray, with publish_markers), /diagnostics
Frames: the world is the pose's header.frame_id. Parameters (all read-only):
``shadow_filter --help``. In full: docs/design/monoslam_nodes.md.
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

from monoslam_shadow_node.common.conversions import (
    CameraInfoWatch,
    features_from_cdr,
    features_from_message,
    pose_from_message,
)
from monoslam_shadow_node.common.frame_sync import FrameSynchronizer
from monoslam_shadow_node.common.notices import LogThrottle, Notice, log_notice
from monoslam_shadow_node.common.pose_link_messages import (
    LINK_SUFFIX,
    PoseLinks,
    link_from_message,
)
from monoslam_shadow_node.shadow_filter.conversions import (
    STATIC_MARKER_LIMIT,
    MarkerTypes,
    TrackFields,
    fill_markers,
    fill_track_array,
    handover_fields,
    revoked_from_message,
    track_array_cdr,
)
from monoslam_shadow_node.shadow_filter.core.shadow_filter import FrameResult, ShadowFilter
from monoslam_shadow_node.shadow_filter.processor import Outcome, ShadowProcessor, ShadowStep
from monoslam_shadow_node.shadow_filter.settings import (
    NODE_NAME,
    PARAMETERS,
    node_settings,
    shadow_config,
)
from slam_core import lazy_stats
from slam_core.arrays import FloatArray
from slam_core.cli import console_main
from slam_core.idle import IdleWatch
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
        lazy_stats.load()
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
        self._idle = IdleWatch(self.settings.sync_horizon_ns / 1e9)  # inputs stopped
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
            self._idle.tick_s,
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
        """The counts on /diagnostics, by name."""
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
        self._idle.note_input()
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
        self._idle.note_input()
        for pose in self._links.on_pose(pose_from_message(message)):
            self._handle(self.processor.add_pose(pose))

    def _on_link(self, message: PoseLink) -> None:
        self._idle.note_input()
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
        if self._idle.idle():
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
