"""monoslam: tracked features and the initialization target in, camera pose and map out.

The MonoSLAM filter of paper 001 (sec. II, ``core.monoslam.MonoSlam``, run by ``processor``):
one EKF over the camera and a map of static point features, started from known points (a
marker of known size and pose, a depth image or a file); with the Shadow filter
(``initialize`` 'handover') the features it hands over as static fix the camera.

Topics:
  subscribes  features (FeatureTrackArray), fiducials (FiducialArray: the target's corners
              are the known points 0-3), camera/camera_info, shadow/static_features and
              shadow/tracks (ShadowTrackArray, with 'handover'), camera/depth/image_raw
              (with known_points_source 'depth')
  publishes   monoslam/pose (PoseWithCovarianceStamped: the camera optical frame in
              map_frame) and monoslam/pose/link (PoseLink), monoslam/path, monoslam/map
              (PointCloud2, transient local), features/predicted (with publish_predictions),
              monoslam/revoked (ShadowTrackArray), /tf (with publish_tf), /diagnostics
Services: ~/save_map (std_srvs/Trigger): write the map's checkpoint now.
Frames: map_frame is defined by the target's pose. Parameters (all read-only; a bad value
stops the node naming it): ``monoslam --help``. In full: docs/design/monoslam_nodes.md.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from functools import partial
from typing import Any

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TransformStamped
from nav_msgs.msg import Path
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage

from monoslam_shadow_node.common.conversions import CameraInfoWatch, features_from_cdr
from monoslam_shadow_node.common.core.inputs import Features
from monoslam_shadow_node.common.frame_sync import StampSync
from monoslam_shadow_node.common.notices import LogThrottle, Notice, log_notice
from monoslam_shadow_node.common.pose_link_messages import LINK_SUFFIX, fill_pose_link
from monoslam_shadow_node.monoslam.conversions import (
    PoseFields,
    TargetSighting,
    cloud_points,
    depth_from_image,
    dynamic_ids_from_cdr,
    fill_cloud,
    fill_pose_stamped,
    fill_pose_with_covariance,
    fill_revoked,
    fill_transform,
    handovers_from_message,
    predictions_cdr,
    revoked_ids,
    target_from_fiducials,
    tum_text,
)
from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
from monoslam_shadow_node.monoslam.core.monoslam_types import TRACKING, MonoSlamResult
from monoslam_shadow_node.monoslam.node_checkpoints import CheckpointsMixin
from monoslam_shadow_node.monoslam.processor import MonoSlamProcessor, MonoSlamStep, Outcome
from monoslam_shadow_node.monoslam.settings import (
    NODE_NAME,
    PARAMETERS,
    known_point_rows,
    monoslam_config,
    node_settings,
    target_settings,
)
from slam_core import lazy_stats
from slam_core.cli import console_main
from slam_core.files import write_atomically
from slam_core.idle import IdleWatch
from slam_core.stamps import stamp_to_ns
from slam_interfaces.msg import (
    FeatureTrackArray,
    FiducialArray,
    PoseLink,
    ShadowTrack,
    ShadowTrackArray,
)
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.qos import latched_qos, output_qos, sensor_qos
from slam_ros.spin import spin_node

FEATURES_TOPIC = 'features'
FIDUCIALS_TOPIC = 'fiducials'
DEPTH_TOPIC = 'camera/depth/image_raw'
CAMERA_INFO_TOPIC = 'camera/camera_info'
HANDOVER_TOPIC = 'shadow/static_features'
SHADOW_TRACKS_TOPIC = 'shadow/tracks'
POSE_TOPIC = 'monoslam/pose'
PATH_TOPIC = 'monoslam/path'
MAP_TOPIC = 'monoslam/map'
PREDICTIONS_TOPIC = 'features/predicted'
REVOKED_TOPIC = 'monoslam/revoked'
INPUT_DEPTH = 100
STATUS_PERIOD_S = 10.0
WAITING_LOG_PERIOD_S = 5.0
DEFAULT_CAMERA_FRAME = 'camera_optical_frame'


class MonoSlamNode(CheckpointsMixin, Node):
    """Thin adapter around MonoSlamProcessor: inputs in, pose and map published."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        values = declare_parameters(self, PARAMETERS)
        lazy_stats.load()
        self.target = target_settings(values)
        rows = known_point_rows(values)
        self.config = monoslam_config(values, self.target, rows)
        self.settings = node_settings(values)
        source = self.config.known_points_source
        self.start_text = {
            'marker': self.target.describe(),
            'depth': f'features with a depth on {DEPTH_TOPIC}',
            'file': f'known points of {values["known_points_file"]}',
        }[source]
        self.processor = MonoSlamProcessor(
            self.config,
            target_text=self.start_text,
            known_rows=rows,
            match_px=self.settings.known_points_match_px,
            depth_tolerance_ns=self.settings.depth_stamp_tolerance_ns,
            map_frame=self.settings.map_frame,
            stamp_tolerance_ns=self.settings.stamp_tolerance_ns,
            sync_horizon_ns=self.settings.sync_horizon_ns,
            queue_size=self.settings.queue_size,
            fiducials_topic=FIDUCIALS_TOPIC,
            camera_info_topic=CAMERA_INFO_TOPIC,
        )
        self._camera_watch = CameraInfoWatch(CAMERA_INFO_TOPIC)
        self._deserialize_features = partial(deserialize_message, message_type=FeatureTrackArray)
        self._deserialize_shadow_tracks = partial(
            deserialize_message, message_type=ShadowTrackArray
        )
        self._camera_frame = DEFAULT_CAMERA_FRAME
        self._throttle = LogThrottle(WAITING_LOG_PERIOD_S)
        self.trajectory: list[PoseFields] = []
        self._path: deque[PoseStamped] = deque(maxlen=self.settings.path_length)
        self._saved_state: tuple[int, ...] | None = None
        self._resume(self.settings.resume_from)
        self._map_changed = self.processor.slam is not None
        self._idle = IdleWatch(self.settings.sync_horizon_ns / 1e9)  # inputs stopped
        self._status_time, self._status_seen = time.monotonic(), (0, 0, 0)
        self.pose_publisher = self.create_publisher(
            PoseWithCovarianceStamped, POSE_TOPIC, output_qos()
        )
        self.link_publisher = self.create_publisher(
            PoseLink, POSE_TOPIC + LINK_SUFFIX, output_qos()
        )
        self.path_publisher = self.create_publisher(Path, PATH_TOPIC, output_qos(depth=1))
        self.map_publisher = self.create_publisher(PointCloud2, MAP_TOPIC, latched_qos())
        self.tf_publisher = (
            self.create_publisher(TFMessage, '/tf', output_qos(depth=100))
            if self.settings.publish_tf
            else None
        )
        self.predictions_publisher = (
            self.create_publisher(FeatureTrackArray, PREDICTIONS_TOPIC, output_qos())
            if self.settings.publish_predictions
            else None
        )
        self.revoked_publisher = (
            self.create_publisher(ShadowTrackArray, REVOKED_TOPIC, output_qos(depth=100))
            if self.config.initialize == 'handover'
            else None
        )
        inputs, info_qos = output_qos(depth=INPUT_DEPTH), sensor_qos(depth=INPUT_DEPTH)
        self.diagnostics = Diagnostics(
            self, self._counts, values=lambda: {'resumed': self.processor.resume_text}
        )
        timed = self.diagnostics.timed
        self.create_subscription(
            FeatureTrackArray, FEATURES_TOPIC, timed(self._on_features, 'features'), inputs,
            raw=True,
        )  # fmt: skip
        if source == 'marker':
            callback = timed(self._on_fiducials, 'fiducials')
            self.create_subscription(FiducialArray, FIDUCIALS_TOPIC, callback, inputs)
        if source == 'depth':
            self.create_subscription(Image, DEPTH_TOPIC, timed(self._on_depth, 'depth'), info_qos)
        self.create_subscription(
            CameraInfo, CAMERA_INFO_TOPIC, timed(self._on_camera_info, 'camera_info'), info_qos
        )
        if self.config.initialize == 'handover':
            self.create_subscription(
                ShadowTrackArray, HANDOVER_TOPIC, timed(self._on_handovers, 'handovers'), inputs
            )
            if self.config.fill_undecided:
                self.create_subscription(
                    ShadowTrackArray,
                    SHADOW_TRACKS_TOPIC,
                    timed(self._on_shadow_tracks, 'shadow_tracks'),
                    inputs,
                    raw=True,
                )
        self.create_service(Trigger, '~/save_map', self._on_save_map)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        period_s = self.settings.checkpoint_period_s
        if period_s > 0 and self.settings.checkpoint_file is not None:
            self.create_timer(period_s, timed(self._on_checkpoint), clock=steady)
        self.create_timer(self._idle.tick_s, timed(self._flush_when_idle), clock=steady)
        self.create_timer(self.settings.map_period_s, timed(self._publish_map), clock=steady)
        self.create_timer(STATUS_PERIOD_S, self._report_status, clock=steady)
        handovers = f' and {HANDOVER_TOPIC}' if self.config.initialize == 'handover' else ''
        self.get_logger().info(
            f'initialize={self.config.initialize}: waiting for {FEATURES_TOPIC}, '
            f'{FIDUCIALS_TOPIC if source == "marker" else DEPTH_TOPIC}{handovers} and '
            f'{CAMERA_INFO_TOPIC}; start from {self.start_text} in {self.settings.map_frame}'
        )

    @property
    def slam(self) -> MonoSlam | None:
        """The filter, None before the first usable camera_info."""
        return self.processor.slam

    @property
    def sync(self) -> StampSync[Features, TargetSighting]:
        """The processor's pairing of features with fiducials."""
        return self.processor.sync

    # --- inputs -----------------------------------------------------------------------------

    def _on_camera_info(self, message: CameraInfo) -> None:
        self._apply_camera(message)
        if self.predictions_publisher is not None:
            self._publish_predictions(stamp_to_ns(message.header.stamp), message.header.frame_id)

    def _apply_camera(self, message: CameraInfo) -> None:
        update = self._camera_watch.update(message)
        if update is None:
            return
        if update.camera is None:
            self.get_logger().error(update.text, throttle_duration_sec=WAITING_LOG_PERIOD_S)
            return
        if message.header.frame_id:
            self._camera_frame = str(message.header.frame_id)
        if update.first:
            self.get_logger().info(update.text)
        else:
            self.get_logger().warning(update.text)
        self._handle(self.processor.set_camera(update.camera))

    def _on_features(self, data: bytes) -> None:  # taken serialized: ``features_from_cdr``
        self._idle.note_input()
        try:
            features = features_from_cdr(data, self._deserialize_features)
        except ValueError as err:  # not what a publisher of the type sends: counted, dropped
            self._handle(self.processor.reject('undecodable', str(err)))
            return
        self._handle(self.processor.add_features(features))
        latest = self.diagnostics.latest_stamp_ns  # what Diagnostics reads off a message
        self.diagnostics.latest_stamp_ns = max(latest or features.stamp_ns, features.stamp_ns)

    def _on_fiducials(self, message: FiducialArray) -> None:
        self._idle.note_input()
        sighting = target_from_fiducials(message, self.target.marker_id, self.target.dictionary)
        self._handle(self.processor.add_sighting(sighting))

    def _on_depth(self, message: Image) -> None:
        self._idle.note_input()  # decoded only while the filter waits for one
        self._handle(self.processor.add_depth(partial(depth_from_image, message)))

    def _on_handovers(self, message: ShadowTrackArray) -> None:
        handovers = handovers_from_message(message)
        for notice in self.processor.add_handovers(handovers, str(message.header.frame_id)):
            self.get_logger().warning(f'{HANDOVER_TOPIC}: {notice.text}')

    def _on_shadow_tracks(self, data: bytes) -> None:  # taken serialized: only ids, statuses
        try:
            ids = dynamic_ids_from_cdr(data, self._deserialize_shadow_tracks)
        except ValueError as err:  # not what a publisher of the type sends: counted, dropped
            self._handle(self.processor.reject('undecodable', str(err)))
            return
        self.processor.mark_moving(ids)

    def _flush_when_idle(self) -> None:
        if self._idle.idle() and self.processor.waiting_features:
            self._handle(self.processor.flush())

    # --- outputs ----------------------------------------------------------------------------

    def _handle(self, outcomes: list[Outcome]) -> None:
        """Log the notices and publish the processed frames, in order."""
        for outcome in outcomes:
            if isinstance(outcome, Notice):
                log_notice(self.get_logger(), outcome, self._throttle, time.monotonic())
            elif isinstance(outcome, MonoSlamStep):
                self._map_changed = True
                if outcome.result.status == TRACKING and outcome.pose is not None:
                    self._publish_pose(outcome.pose)
                self._publish_revoked(outcome.result)

    def _publish_pose(self, fields: PoseFields) -> None:
        frame = self.settings.map_frame
        if fields.cross_stamps:  # before the pose (pose_link_messages)
            link = fill_pose_link(
                fields.stamp_ns,
                fields.cross_stamps,
                fields.cross_covariances,
                frame,
                PoseLink(),
                Time,
            )
            self.link_publisher.publish(link)
        self.pose_publisher.publish(
            fill_pose_with_covariance(fields, frame, PoseWithCovarianceStamped())
        )
        self._path.append(fill_pose_stamped(fields, frame, PoseStamped()))
        if self.path_publisher.get_subscription_count():
            path = Path(poses=list(self._path))
            path.header = self._path[-1].header
            self.path_publisher.publish(path)
        if self.tf_publisher is not None:
            child = self.settings.tf_camera_frame
            transform = fill_transform(fields, frame, child, TransformStamped())
            self.tf_publisher.publish(TFMessage(transforms=[transform]))
        if self.settings.trajectory_file is not None:
            self.trajectory.append(fields)

    def _publish_revoked(self, result: MonoSlamResult) -> None:
        """Hand the features revoked in this frame back to the Shadow filter."""
        revoked = revoked_ids(result)
        if self.revoked_publisher is None or not revoked:
            return
        self.revoked_publisher.publish(
            fill_revoked(
                revoked, result.stamp_ns, self.settings.map_frame, ShadowTrackArray(),
                ShadowTrack,
            )
        )  # fmt: skip
        self.get_logger().info(
            f'revoked {len(revoked)} feature(s) that moved (handed over or filled undecided): '
            f'{", ".join(map(str, revoked))} (back to the Shadow filter on {REVOKED_TOPIC})'
        )

    def _publish_map(self) -> None:
        if self.processor.slam is None or not self._map_changed:
            return
        self._map_changed = False
        stamp_ns = self.processor.sync.last_ns or 0
        points = cloud_points(self.processor.map_points())
        self.map_publisher.publish(
            fill_cloud(points, stamp_ns, self.settings.map_frame, PointCloud2(), PointField)
        )

    def _publish_predictions(self, stamp_ns: int, frame_id: str) -> None:
        """Publish the owned features' predicted pixels for the image at ``stamp_ns``."""
        predicted = self.processor.predictions(stamp_ns)
        if predicted is None or self.predictions_publisher is None:
            return
        ids, pixels, covariances, warps = predicted
        frame_id = frame_id or self._camera_frame
        self.predictions_publisher.publish(  # serialized from one numpy array
            predictions_cdr(ids, pixels, stamp_ns, frame_id, covariances, warps)
        )

    def _counts(self) -> dict[str, int]:
        """The counts on /diagnostics: the processor's, and camera_infos rejected."""
        counts = self.processor.counts
        return {
            'processed': counts.processed,
            'without fiducials': counts.alone,
            'skipped': counts.skipped,
            'dropped': counts.dropped_total,
            'handovers accepted': counts.accepted,
            'handovers refused': counts.refused,
            'lost': counts.lost,
            'depth images': counts.depth_received,
            'depth images not needed': counts.depth_unused,
            'predictions': counts.predictions,
            'predictions skipped (behind)': counts.predictions_behind,
            'resumes predicted': counts.resumes_predicted,
            'resumes re-localised': counts.resumes_relocalised,
            'measured': counts.measured,
            'camera_info rejected': self._camera_watch.rejected,
        }

    def _report_status(self) -> None:
        counts = self.processor.counts
        now, seen = time.monotonic(), (counts.processed, counts.skipped, counts.dropped_total)
        if seen == self._status_seen:
            return  # nothing came since the last line
        rate = (counts.processed - self._status_seen[0]) / (now - self._status_time)
        self.get_logger().info(self.processor.status_line(rate))
        self._status_time, self._status_seen = now, seen

    def write_trajectory(self) -> None:
        """Write the trajectory file (TUM text, atomically), if one is configured."""
        path = self.settings.trajectory_file
        if path is None:
            return
        try:
            write_atomically(path, tum_text(self.trajectory))
        except OSError as err:
            self.get_logger().error(f'trajectory_file {str(path)!r} not written: {err}')
            return
        self.get_logger().info(f'trajectory ({len(self.trajectory)} poses) written to {path}')

    def destroy_node(self) -> None:
        """Write the trajectory and the checkpoint, log the final summary, then destroy."""
        self.write_trajectory()
        if self.settings.checkpoint_period_s > 0 and self.processor.slam is not None:
            try:
                self.save_checkpoint()
            except OSError as err:
                self.get_logger().error(f'could not write the checkpoint: {err}')
        counts = self.processor.counts
        if counts.processed or counts.dropped_total or counts.skipped:
            self.get_logger().info(f'done: {self.processor.status_line()}')
        super().destroy_node()


@console_main(NODE_NAME)
def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C (the Jazzy shutdown pattern)."""
    return spin_node(NODE_NAME, MonoSlamNode, argv, parameters=PARAMETERS, doc=__doc__)


if __name__ == '__main__':
    sys.exit(main())
