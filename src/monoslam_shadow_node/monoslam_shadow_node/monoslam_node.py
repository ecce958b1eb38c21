"""monoslam: tracked features and the initialization target in, camera pose and map out.

The MonoSLAM filter of paper 001 (sec. II, ``core.monoslam.MonoSlam``; the pairing, state and
counts: ``monoslam_processor``): one EKF over the camera and a map of static point features.
It starts from known points (a marker of known size and pose, a depth image or a file: a
monocular camera cannot observe scale), and with the Shadow filter (``initialize``
'handover') the features it hands over as static fix the camera.

Topics:
  subscribes  features (slam_interfaces/FeatureTrackArray, reliable, depth 100): track ids and
              raw (distorted) pixels of one image, header.stamp = the image stamp.
              fiducials (slam_interfaces/FiducialArray, reliable, depth 100): marker_detector's
              detections in the same image (one message per image, empty when nothing was
              found); the target's corners (TL, TR, BR, BL raw pixels) are the known points
              0-3 of the frame.
              camera/camera_info (sensor_msgs/CameraInfo, best effort, depth 100 as it is taken
              in step with features): intrinsics and plumb_bob/rational_polynomial distortion;
              a change is applied from the next frame on and logged. With publish_predictions
              it also triggers the predictions for the image of its stamp (once per image,
              before the tracker tracks that image).
              shadow/static_features (slam_interfaces/ShadowTrackArray, reliable, depth 100),
              when initialize is 'handover': features the Shadow filter handed over as STATIC
              (world position and covariance in map_frame); each enters the map when next
              observed. A handover that is not STATIC, not finite, not positive
              semi-definite or in another frame is refused and logged with its id.
              camera/depth/image_raw (sensor_msgs/Image 16UC1 mm or 32FC1 m, best effort,
              depth 100), with known_points_source 'depth': held until the start.
              shadow/tracks (slam_interfaces/ShadowTrackArray, reliable, depth 100), when
              initialize is 'handover' and fill_undecided: the features the Shadow filter
              found DYNAMIC never fill the map undecided, and leave it if they had.
  publishes   monoslam/pose (geometry_msgs/PoseWithCovarianceStamped, reliable, depth 10),
              every frame with a pose (tracking): the pose of the camera OPTICAL frame (x right,
              y down, z forward) in map_frame, R_world_camera and the optical centre, covariance
              in ROS order (x, y, z, rotation about the map's X, Y, Z axes) -- what
              shadow_filter's pose_topic expects. Just before it, monoslam/pose/link
              (slam_interfaces/PoseLink): the pose error's covariances with the errors of
              the earlier poses the filter remembers (core/monoslam_state.POSE_HISTORY).
              monoslam/path (nav_msgs/Path, reliable, depth 1), every frame with a pose while
              someone subscribes: the latest path_length poses.
              monoslam/map (sensor_msgs/PointCloud2, reliable, transient local), at most every
              map_period_s when it changed: every map point with a defined position (active
              and retired), fields x, y, z (float32, m), sigma_m (float32, the largest
              standard deviation, m), id (float64, the track id), active (uint8: 1 in the
              filter, 0 retired), handover (uint8: 1 handed over by the Shadow filter).
              /tf (tf2_msgs/TFMessage, reliable, depth 100), when publish_tf is true: map_frame
              -> tf_camera_frame (the optical frame as MonoSLAM places it) at the image
              stamp, under MonoSLAM's own frame names: the camera's real optical frame keeps
              its one parent in the robot's tree (REP 105), and the robot's map belongs to
              the SLAM that publishes map -> odom. Off by default: use monoslam/pose.
              features/predicted (slam_interfaces/FeatureTrackArray, reliable, depth 10), when
              publish_predictions is true: per camera_info stamp after the last processed
              frame, the predicted raw pixels of the features the filter owns (for
              feature_tracker's use_predictions); empty while it has none, is not tracking
              or is behind (the image before is not processed: it would come late; counted).
              monoslam/revoked (slam_interfaces/ShadowTrackArray, reliable, depth 100), when
              initialize is 'handover', in frames that revoke: handed-over features that
              failed the persistent-outlier test (they moved after all), status DYNAMIC, no
              position (position_covariance[0] = -1), header.stamp = the image stamp; the
              Shadow filter takes them back as suspects. Each is also logged.
              /diagnostics (diagnostic_msgs/DiagnosticArray, every second): inputs received
              and dropped, frames processed and skipped, handovers, losses, resumes that
              predicted over the gap and that re-localised, 'resumed' (what the last resume
              did, 'no' for a fresh start), processing time, lag (slam_ros.diagnostics)
  Nothing published is ever NaN: a pose that is not finite is not published (an error is
  logged), and map points or predictions that are not finite are left out.
Services:
  ~/save_map (std_srvs/Trigger)   write the map's checkpoint to checkpoint_file now.

Synchronization (frame_sync): features and fiducials pair when their stamps differ by at most
stamp_tolerance_s, and are processed in stamp order. A features frame whose fiducials have
not come once the newest stamp seen is sync_horizon_s past it (or no input came for
sync_horizon_s of wall time) is processed without them once the filter has started (said in
a throttled warning), and dropped before (the filter needs the target to start). Features
before any camera_info are held until it comes.

Logs: waiting for the target (throttled), the start, tracking lost (why), a resume, a
camera_info change, every bad input with its culprit (the node goes on), and every 10 s a
status line (rate, state, map, the update's counts, handovers, losses, skips and drops).

Parameters (filter): the fields of the core's MonoSlamConfig, one to one (four renamed with
their unit); their defaults are the core's, written out in config/monoslam.yaml (a test
keeps the two equal).
  pixel_sigma_px                  feature and target corner pixel noise, px.
  tracking_offset_px, tracking_offset_time_s  tracked features' offsets that persist
                                  between images, px, and their correlation time, s (the
                                  shadow_filter's parameters); with offsets, each feature
                                  keeps its own in the state (2 states, Gauss-Markov).
  estimate_noise (true)           the tracker's noise estimated from the measured tracks
                                  (core.noise_monitor) and taken once a second: white at
                                  least pixel_sigma_px, offsets when they matter; the
                                  status line says which is in force.
  linear_acceleration_sigma_m_s2, angular_acceleration_sigma_rad_s2  constant velocity
                                  model noise, m/s^2 and rad/s^2 per sqrt(Hz).
  initial_velocity_sigma_m_s, initial_angular_velocity_sigma_rad_s  camera velocity
                                  uncertainty at the start, m/s and rad/s.
  initial_inverse_depth_per_m, initial_inverse_depth_sigma_per_m  a new feature's inverse
                                  depth and its sigma (initialize 'all'), 1/m.
  second_order                    add the inverse depth x baseline term to an
                                  inverse-depth feature's innovation covariance (true).
  gate_probability                chi-square gate of each measurement.
  linearity_threshold             inverse depth -> Euclidean below this linearity index.
  max_features                    most features in the filter.
  target_measured, max_new_per_frame, min_new_spacing_px  initialize 'all': add features
                                  while fewer are measured, at most this many per frame,
                                  at least this far apart (px).
  max_view_angle_deg (45), view_margin_px (11)  a map feature is searched for only within
                                  this angle of its first ray and this far inside the image
                                  (the tracker's border margin and half its window).
  failure_window, min_success_ratio, max_consecutive_failures  deleting failing features.
  lost_after_frames, max_position_sigma_m  tracking is lost after this many frames measuring
                                  nothing, or when the position sigma exceeds this (m).
  lost_after_known_rejected_frames (3)  ... or after this many frames in a row in which the
                                  gate rejected more than half of the target's corners in
                                  view: the estimate has diverged from the known points.
                                  (It is also lost when its pose covariance is no longer
                                  positive definite: such a covariance is never published.)
  max_gap_s                       a longer gap between frames is logged, s.
  initialize ('handover')         'handover' (with the Shadow filter) or 'all' (classic
                                  MonoSLAM alone, from every new track).
  handover_probation (true)       a handed-over feature corrects only its own estimate (a
                                  Schmidt consider update), not the camera, until its
                                  inverse depth becomes Euclidean (SLAM's own views fix it),
                                  or while fewer than 5 others are measured in a frame.
  fill_undecided (true)           with initialize 'handover', features the Shadow filter
                                  has not decided on fill the map; found DYNAMIC or
                                  failing: revoked.
  undecided_probation (false)     such a feature corrects only itself (a consider update:
                                  never the camera) until the Shadow filter clears it.
  new_probation (false)           initialize 'all': a new feature corrects only itself until
                                  its inverse depth becomes Euclidean, as a handover does
                                  (the oracle graph monoslam_labelled_rgbd.yaml sets it).
  known_points_source ('marker')  what fixes the world and its scale at the start: 'marker'
                                  (the target below), 'depth' (the features with a depth in
                                  the first camera/depth/image_raw paired with a features
                                  frame; map_frame is then that camera's optical frame) or
                                  'file' (known_points_file).
  depth_noise_per_m (1.425e-3), depth_start_points (50)  'depth': the sensor's noise,
                                  sigma_z = c z^2, and most features the start maps.
  update ('ransac'), ransac_seed (0)  'ransac': the 1-point RANSAC update (Civera et al.
                                  2010), its draws seeded for reproducible runs; 'gated':
                                  every measurement inside the chi-square gate.
Parameters (initialization target): its four corners are the known points.
  target_id (0), target_dictionary ('DICT_APRILTAG_36h11')  the marker, as marker_detector
                                  reports it.
  target_size_m (0.16)            side of its black square, m (marker_detector's default
                                  marker size; set it to the printed marker's).
  target_xyz_m ([0, 0, 0]), target_rpy_rad ([0, 0, 0])  the pose of the marker frame (x right,
                                  y up, z out of the printed face) in map_frame: centre, m,
                                  and roll, pitch, yaw about the fixed X, Y, Z axes, rad. The
                                  default puts the marker at the map origin: it defines the
                                  map.
Parameters (node):
  map_frame ('monoslam_map')      frame of the pose, path, map and TF (the target's world,
                                  not the robot's map).
  publish_tf (false)              publish the TF above.
  tf_camera_frame ('monoslam_camera')  its child frame; must differ from map_frame.
  publish_predictions (false)     publish features/predicted.
  path_length (3000)              poses kept in monoslam/path.
  map_period_s (1.0)              shortest period of monoslam/map, s.
  stamp_tolerance_s (0.0)         largest features-to-fiducials stamp difference, s.
  sync_horizon_s (0.5)            how long a features frame waits for its fiducials, s.
  queue_size (100)                waiting feature frames and fiducial arrays, each.
  trajectory_file ('')            on shutdown (Ctrl-C too) write the trajectory there as
                                  TUM text ('stamp_s x y z qx qy qz qw' per pose, the
                                  optical frame in map_frame), atomically; '' for none.
  checkpoint_period_s (10.0)      save the checkpoint this often when the map changed (and on
                                  shutdown); 0 = only on ~/save_map.
  checkpoint_file ('')            the checkpoint (monoslam_checkpoint: .npz, atomic): camera
                                  state, every feature's parameters and track id, the full
                                  covariance, template views and counters, the target
                                  initialization state, the last stamp; '' = none.
  known_points_file (''), known_points_match_px (3.0)  'file': CSV id,x,y,z,u,v (position
                                  in map_frame, m; raw pixel in the first image): the track
                                  nearest each pixel, within the match distance, is that point.
  depth_stamp_tolerance_s (0.02)  'depth': largest features-to-depth stamp difference, s.
  resume_from ('')                start from this checkpoint; 'auto' = checkpoint_file when it
                                  exists (a GRAPH's respawn_parameters); a bad one stops the
                                  node naming it. The first frame after it predicts over the
                                  gap, or, if too long (core.monoslam_snapshot), re-localises
                                  from the target; the log and /diagnostics say which.
All are read-only; a bad value stops the node with an error naming the parameter.

Frames: map_frame is defined by the target's pose; features and fiducials are in the camera
optical frame of the camera_info.
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

from monoslam_shadow_node.conversions import CameraInfoWatch, Features, features_from_cdr
from monoslam_shadow_node.core.monoslam import MonoSlam
from monoslam_shadow_node.core.monoslam_types import TRACKING, MonoSlamResult
from monoslam_shadow_node.frame_sync import StampSync
from monoslam_shadow_node.monoslam_conversions import (
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
from monoslam_shadow_node.monoslam_node_checkpoints import CheckpointsMixin
from monoslam_shadow_node.monoslam_processor import MonoSlamProcessor, MonoSlamStep, Outcome
from monoslam_shadow_node.monoslam_settings import (
    NODE_NAME,
    PARAMETERS,
    known_point_rows,
    monoslam_config,
    node_settings,
    target_settings,
)
from monoslam_shadow_node.notices import LogThrottle, Notice, log_notice
from monoslam_shadow_node.pose_link_messages import LINK_SUFFIX, fill_pose_link
from slam_core.cli import console_main
from slam_core.files import write_atomically
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
    """Thin adapter around MonoSlamProcessor: features, fiducials and handovers in, pose and
    map published."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        values = declare_parameters(self, PARAMETERS)
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
        self._last_input = time.monotonic()
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
        horizon_s = self.settings.sync_horizon_ns / 1e9
        self.create_timer(max(horizon_s / 2, 0.05), timed(self._flush_when_idle), clock=steady)
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
        self._last_input = time.monotonic()
        try:
            features = features_from_cdr(data, self._deserialize_features)
        except ValueError as err:  # not what a publisher of the type sends: counted, dropped
            self._handle(self.processor.reject('undecodable', str(err)))
            return
        self._handle(self.processor.add_features(features))
        latest = self.diagnostics.latest_stamp_ns  # what Diagnostics reads off a message
        self.diagnostics.latest_stamp_ns = max(latest or features.stamp_ns, features.stamp_ns)

    def _on_fiducials(self, message: FiducialArray) -> None:
        self._last_input = time.monotonic()
        sighting = target_from_fiducials(message, self.target.marker_id, self.target.dictionary)
        self._handle(self.processor.add_sighting(sighting))

    def _on_depth(self, message: Image) -> None:
        self._last_input = time.monotonic()  # decoded only while the filter waits for one
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
        idle_s = time.monotonic() - self._last_input
        if self.processor.waiting_features and idle_s > self.settings.sync_horizon_ns / 1e9:
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
