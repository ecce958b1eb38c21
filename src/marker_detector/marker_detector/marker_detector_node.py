"""marker_detector: camera images in, fiducial poses and range-bearing observations out.

Detects square fiducials (cv2.aruco; AprilTag 36h11 by default) in each image, refines the
corners to subpixel accuracy, solves each marker's pose (IPPE square) with a covariance from
the reprojection Jacobian and the pixel noise, applies the quality gates and converts the
marker centres into range and bearing in the robot base frame. The lens (plumb-bob or
rational polynomial from camera_info) is undistorted inside the pose solution. Bad inputs
(an unsupported encoding, an empty or corrupt image, no camera mount) are logged with the
reason, and the node goes on with the next image. Images that come before the first usable
camera_info, or (extrinsics_source 'tf_static') before the camera mount of their frame on
/tf_static (drivers and the mount's publisher start together, and discovery between
processes takes a second or two, longer on a loaded machine), are held, those of the last
5 s of stamps (at most 64 MiB of images), and detected in order once both are there; older
ones are dropped and counted, with the reason in the log.

Topics:
  subscribes  camera/image_raw (sensor_msgs/Image: mono8, bgr8, rgb8, bgra8, rgba8) when
              image_transport is 'raw', or camera/image_raw/compressed
              (sensor_msgs/CompressedImage) when it is 'compressed'; best effort
              camera/camera_info (sensor_msgs/CameraInfo, best effort)
              /tf_static (tf2_msgs/TFMessage, transient local) when extrinsics_source is
              'tf_static'
  publishes   fiducials (slam_interfaces/FiducialArray, camera optical frame, every image;
              empty, header only, for an image not searched: detect_every_n_frames)
              landmark_observations (slam_interfaces/LandmarkObservationArray, base frame,
              only for images with at least one accepted marker; reliable, depth 1000, so
              that a mapper busy solving does not lose them from this side; transient-local,
              so a restarted mapper gets the last 1000 again: 100 s of 10 Hz images)
              ~/debug_image (sensor_msgs/Image bgr8, when publish_debug_image is true)
              /diagnostics (diagnostic_msgs/DiagnosticArray, every second): images
              received, processed, dropped and held, markers, whole-image and box
              searches, processing time, lag (slam_ros.diagnostics)

Parameters:
  dictionary ('DICT_APRILTAG_36h11')  cv2.aruco dictionary: AprilTag 16h5/25h9/36h10/36h11,
                              ArUco DICT_4X4_50 ... DICT_7X7_1000, DICT_ARUCO_ORIGINAL.
  marker_size_m (0.16)        side of the black square of every marker, m (> 0).
  marker_sizes_m ([])         per-id sizes overriding it, entries 'id:size_m' (e.g. '7:0.14').
  corner_refinement ('subpix')  'subpix', 'contour', 'apriltag' or 'none'.
  min_side_px (12.0)          reject markers whose shortest side is shorter, px.
  max_reprojection_error_px (2.0)  reject poses whose RMS corner reprojection error is larger.
  max_range_m (8.0)           reject markers farther from the camera, m.
  max_viewing_angle_rad (1.22)  reject markers seen more obliquely (normal vs line of sight).
  allowed_ids ([])            only these ids, entries 'id' or 'first-last' (e.g. '0-28');
                              empty: all.
  pixel_noise_px (0.5)        corner noise sigma behind the pose covariance, px.
  image_transport ('raw')     'raw' (Image) or 'compressed' (CompressedImage).
  max_image_pixels (16777216)  larger images (4096 x 4096) are refused before they are
                              decoded or copied (a PNG's or JPEG's size from its header);
                              counted as 'refused too large'. 0: no limit.
  base_frame ('base_link')    frame of the range-bearing observations.
  extrinsics_source ('tf_static')  'tf_static' (chain base_frame -> image frame on
                              /tf_static) or 'parameters' (camera_xyz_m, camera_rpy_rad).
  camera_xyz_m ([0, 0, 0]), camera_rpy_rad ([0, 0, 0])  camera_link in base_frame; the
                              optical frame follows REP 103 (z forward, x right, y down).
  search_period_frames (1)    search the whole image every this many frames; in the frames
                              between, only a box about each marker of the frame before
                              (its corners grown by search_margin_px plus half its side),
                              and the whole image again when a box misses it. A few markers
                              followed at a camera's rate then cost a fraction of a frame's
                              time; a marker newly in view is found at most
                              search_period_frames - 1 frames late. 1: every frame. With
                              allowed_ids set, no whole-image search while every allowed id
                              is followed (nothing else could be found).
  search_margin_px (32.0)     how far a followed marker may move between frames and still be
                              found in its box, px (32: a turn of 1.8 rad/s at fx 525 px and
                              30 Hz); a marker that moves farther is found by the whole-image
                              search that follows in the same frame (time, not detections).
  detect_every_n_frames (1)   detect in every this many images (the first, then every n-th);
                              an image between is not decoded, and its fiducials message is
                              empty (header only), so that a node pairing fiducials with the
                              image's other data (monoslam) does not wait for them; counted
                              as 'not searched'. A marker newly in view is found at most
                              n - 1 images late. 1: every image.
  publish_debug_image (false)  publish the image with the detections drawn.

The detector settings (dictionary to pixel_noise_px) can be changed at run time with
`ros2 param set`; an invalid value (e.g. a marker size <= 0) is refused with the reason and
the node keeps its previous settings.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from typing import Any

import cv2
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from tf2_msgs.msg import TFMessage

from marker_detector.conversions import (
    camera_info_fields,
    check_message_size,
    fill_fiducials,
    fill_observations,
    image_from_message,
    transform_matrix,
)
from marker_detector.core.images import ImageError, ImageTooLargeError
from marker_detector.processor import FrameOutput, InputError, MarkerProcessor
from marker_detector.settings import (
    PARAMETERS,
    detector_config,
    extrinsics_config,
    search_plan,
)
from slam_core.cli import console_main
from slam_core.errors import ParameterError
from slam_core.stamps import stamp_to_ns
from slam_interfaces.msg import (
    FiducialArray,
    FiducialDetection,
    LandmarkObservation,
    LandmarkObservationArray,
)
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters, updated_values
from slam_ros.qos import latched_qos, output_qos, replayed_qos, sensor_qos
from slam_ros.spin import spin_node

STATUS_PERIOD_S = 10.0


def draw_detections(image: np.ndarray, output: FrameOutput) -> np.ndarray:
    """Return a BGR copy of ``image`` with accepted markers (green) and their ids drawn."""
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    for detection in output.detections:
        corners = np.round(np.asarray(detection.corners_px)).astype(np.int32)
        cv2.polylines(canvas, [corners], isClosed=True, color=(0, 255, 0), thickness=2)
        cv2.circle(canvas, tuple(int(v) for v in corners[0]), 4, (0, 0, 255), -1)
        label = f'{detection.id} {detection.range_m:.2f}m'
        cv2.putText(
            canvas,
            label,
            tuple(int(v) for v in corners[0]),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            (255, 0, 0),
            1,
        )
    return canvas


HOLD_S = 5.0
"""Images held while no camera_info or camera mount has come yet span at most this much stamp
time (the oldest is dropped first). DDS discovery sends its first announcements within a
fraction of a second and then one every 3 s (Fast DDS's default period): 5 s covers a missed
first burst and the next periodic announcement, on a loaded machine too."""

HOLD_MAX_BYTES = 64 * 2**20
"""And at most this many image bytes (5 s of 640x480 mono8 at 30 Hz is 46 MB)."""


class DetectorBehaviour(Node):
    """marker_detector on an rclpy node, plain (MarkerDetectorNode) or lifecycle
    (marker_detector_lifecycle): ``_configure`` builds the processor and publishers,
    ``_activate`` the subscriptions, ``_deactivate`` removes them again."""

    def _configure(self, values: dict[str, Any]) -> None:
        self.processor = MarkerProcessor(
            detector_config(values), extrinsics_config(values), search_plan(values)
        )
        self._values = values
        self.publish_debug = bool(values['publish_debug_image'])
        self.images = 0
        self.dropped = 0
        self.detect_every = int(values['detect_every_n_frames'])
        self.not_searched = 0
        self.detections = 0
        self.too_large = 0
        self.camera_info_rejected = 0
        self.tf_rejected = 0
        self.max_image_pixels = int(values['max_image_pixels'])
        self.held: deque[Image | CompressedImage] = deque()
        self._held_bytes = 0
        self._status_time = time.monotonic()
        self._status_images = 0
        self.diagnostics = Diagnostics(self, self._counts)
        self.fiducials_publisher = self.create_publisher(FiducialArray, 'fiducials', output_qos())
        self.observations_publisher = self.create_publisher(
            LandmarkObservationArray, 'landmark_observations', replayed_qos(depth=1000)
        )
        self.debug_publisher = (
            self.create_publisher(Image, '~/debug_image', output_qos(depth=2))
            if self.publish_debug
            else None
        )
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._inputs: list[Any] = []

    def _activate(self, values: dict[str, Any]) -> None:
        """Take images, camera_info and the camera mount."""
        timed = self.diagnostics.timed
        transport = str(values['image_transport'])
        if transport == 'raw':
            image = self.create_subscription(
                Image, 'camera/image_raw', timed(self._on_image, 'image'), sensor_qos()
            )
        else:
            image = self.create_subscription(
                CompressedImage,
                'camera/image_raw/compressed',
                timed(self._on_image, 'image'),
                sensor_qos(),
            )
        info = self.create_subscription(
            CameraInfo,
            'camera/camera_info',
            timed(self._on_camera_info, 'camera_info'),
            sensor_qos(),
        )
        self._inputs = [image, info]
        if self.processor.extrinsics.source == 'tf_static':
            self._inputs.append(
                self.create_subscription(
                    TFMessage,
                    '/tf_static',
                    timed(self._on_tf_static, 'tf_static'),
                    latched_qos(depth=100),
                )
            )

    def _deactivate(self) -> None:
        """Stop taking inputs; camera_info and the mount already taken stay."""
        for subscription in self._inputs:
            self.destroy_subscription(subscription)
        self._inputs = []

    def _finalize(self) -> None:
        """Forget the parameter-change check (the lifecycle node's cleanup)."""
        self.remove_on_set_parameters_callback(self._on_set_parameters)

    def _error(self, message: str) -> None:
        self.get_logger().error(message, throttle_duration_sec=2.0)

    def _on_set_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        try:
            values = updated_values(PARAMETERS, self._values, parameters)
            config = detector_config(values)
        except ParameterError as err:
            self.get_logger().error(f'parameter change refused, settings kept: {err}')
            return SetParametersResult(successful=False, reason=str(err))
        self.processor.reconfigure(config)
        self._values = values
        self.get_logger().info(
            'detector settings changed: ' + ', '.join(p.name for p in parameters)
        )
        return SetParametersResult(successful=True)

    def _on_camera_info(self, message: CameraInfo) -> None:
        try:
            self.processor.set_camera_info(**camera_info_fields(message))
        except InputError as err:
            self.camera_info_rejected += 1
            self._error(f'{err} ({self.camera_info_rejected} rejected so far)')
            return
        self._release_held('camera_info')

    def _on_tf_static(self, message: TFMessage) -> None:
        for transform in message.transforms:
            try:
                self.processor.transforms.add(
                    transform.header.frame_id,
                    transform.child_frame_id,
                    transform_matrix(transform.transform),
                )
            except InputError as err:
                self.tf_rejected += 1
                self._error(f'/tf_static: {err} ({self.tf_rejected} rejected so far)')
        self._release_held('the camera mount')

    def _release_held(self, what: str) -> None:
        """Detect the held images that can now be (in order), after ``what`` arrived."""
        if not self.held or self._missing(self.held[0].header.frame_id) is not None:
            return
        self.get_logger().info(
            f'{what} arrived: detecting in the {len(self.held)} images held until now'
        )
        while self.held and self._missing(self.held[0].header.frame_id) is None:
            image = self.held.popleft()
            self._held_bytes -= len(image.data)
            self._detect(image)

    def _missing(self, frame_id: str) -> str | None:
        """What an image in ``frame_id`` waits for (None: nothing)."""
        processor = self.processor
        if processor.camera is None:
            return processor.no_camera_reason()
        source = processor.extrinsics.source
        base = processor.extrinsics.base_frame
        if source == 'tf_static' and processor.transforms.lookup(base, frame_id) is None:
            return f'no camera mount {base!r} -> {frame_id!r} on /tf_static yet'
        return None

    def _on_image(self, message: Image | CompressedImage) -> None:
        try:
            check_message_size(message, self.max_image_pixels)
        except ImageTooLargeError as err:
            self.images += 1
            self.dropped += 1
            self.too_large += 1
            if self.too_large == 1:
                self.get_logger().warning(
                    f'{err}; the next ones are only counted (refused too large)'
                )
            return
        missing = self._missing(message.header.frame_id)
        if missing is not None or self.held:
            self._hold(message, missing or 'older images are held')
            return
        self._detect(message)

    def _detect(self, message: Image | CompressedImage) -> None:
        self.images += 1
        if (self.images - 1) % self.detect_every:  # not due: said empty (module docstring)
            self.not_searched += 1
            empty = FiducialArray()  # stamped and framed as a searched image's would be
            empty.header.stamp = message.header.stamp
            empty.header.frame_id = self.processor.image_frame(message.header.frame_id)
            self.fiducials_publisher.publish(empty)
            self._report_status()
            return
        stamp_ns = stamp_to_ns(message.header.stamp)
        try:
            image = image_from_message(message, self.max_image_pixels)
            output = self.processor.process(stamp_ns, message.header.frame_id, image)
        except (ImageError, InputError) as err:
            self.dropped += 1
            self._error(f'image dropped ({self.dropped} so far): {err}')
            return
        self.detections += len(output.detections)
        self.fiducials_publisher.publish(
            fill_fiducials(output, FiducialArray(), FiducialDetection)
        )
        if output.observations:
            self.observations_publisher.publish(
                fill_observations(output, LandmarkObservationArray(), LandmarkObservation)
            )
        if self.debug_publisher is not None and self.debug_publisher.get_subscription_count():
            self.debug_publisher.publish(self._debug_image(image, output, message))
        self._report_status()

    def _hold(self, message: Image | CompressedImage, missing: str) -> None:
        """Keep an image that cannot be detected yet (module docstring)."""
        self.held.append(message)
        stamp_ns = stamp_to_ns(message.header.stamp)
        hint = '' if 'camera_info' in missing else '; is the camera mount published on /tf_static?'

        self._held_bytes += len(message.data)
        while len(self.held) > 1 and (
            stamp_ns - stamp_to_ns(self.held[0].header.stamp) > HOLD_S * 1e9
            or self._held_bytes > HOLD_MAX_BYTES
        ):
            oldest = self.held.popleft()
            self._held_bytes -= len(oldest.data)
            self.images += 1
            self.dropped += 1
            self._error(
                f'image dropped ({self.dropped} so far): {missing}, and images are held for '
                f'at most {HOLD_S:g} s (the image at {stamp_to_ns(oldest.header.stamp)} ns)'
                f'{hint}'
            )
        self.get_logger().warning(
            f'{missing}: image at {stamp_ns} ns held ({len(self.held)} held, for at most '
            f'{HOLD_S:g} s) until it arrives{hint}',
            throttle_duration_sec=2.0,
        )

    def _debug_image(self, image: np.ndarray, output: FrameOutput, source: Any) -> Image:
        canvas = draw_detections(image, output)
        debug = Image()
        debug.header = source.header
        debug.height, debug.width = canvas.shape[:2]
        debug.encoding = 'bgr8'
        debug.step = canvas.shape[1] * 3
        debug.data = canvas.tobytes()
        return debug

    def _counts(self) -> dict[str, int]:
        """The counts on /diagnostics: images processed (those not searched among them),
        dropped (bad, or no camera_info in time; of them refused too large) and held for a
        camera_info, markers accepted, camera_info messages and /tf_static transforms
        rejected."""
        return {
            'processed': self.images - self.dropped,
            'dropped': self.dropped,
            'refused too large': self.too_large,
            'camera_info rejected': self.camera_info_rejected,
            'tf_static rejected': self.tf_rejected,
            'held': len(self.held),
            'not searched': self.not_searched,
            'markers': self.detections,
            'whole-image searches': self.processor.search.full_searches,
            'box searches': self.processor.search.box_searches,
        }

    def _report_status(self) -> None:
        now = time.monotonic()
        if now - self._status_time < STATUS_PERIOD_S:
            return
        rate = (self.images - self._status_images) / (now - self._status_time)
        self.get_logger().info(
            f'{self.images} images ({rate:.1f}/s), {self.detections} markers accepted, '
            f'{self.dropped} images dropped'
            + (f', {self.not_searched} not searched' if self.detect_every > 1 else '')
        )
        self._status_time, self._status_images = now, self.images


class MarkerDetectorNode(DetectorBehaviour):
    """marker_detector as a plain node: configured and active from the start."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('marker_detector', **kwargs)
        values = declare_parameters(self, PARAMETERS)
        self._configure(values)
        self._activate(values)


@console_main('marker_detector')
def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C (the Jazzy shutdown pattern)."""
    return spin_node(
        'marker_detector', MarkerDetectorNode, argv, parameters=PARAMETERS, doc=__doc__
    )


if __name__ == '__main__':
    sys.exit(main())
