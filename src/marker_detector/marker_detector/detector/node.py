"""marker_detector: camera images in, fiducial poses and range-bearing observations out.

Detects square fiducials (cv2.aruco; AprilTag 36h11 by default), solves each marker's pose
and covariance, applies the quality gates and gives each marker centre's range and bearing in
the base frame. Bad inputs are logged and skipped. Images before the first camera_info or
camera mount are held, those of the last 5 s of stamps (at most 64 MiB of images), and
detected in order once both are there; older ones are dropped and counted.

Topics:
  subscribes  camera/image_raw (Image) or camera/image_raw/compressed (CompressedImage), per
              image_transport; camera/camera_info; /tf_static (the camera mount), best effort
  publishes   fiducials (FiducialArray, camera optical frame, every image), landmark_
              observations (LandmarkObservationArray, base frame, every image, empty when
              nothing is seen, reliable, transient-local, 1000), ~/debug_image (with
              publish_debug_image), /diagnostics
Detector settings change at run time (ros2 param set). In full: docs/design/marker_nodes.md
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

from marker_detector.common.conversions import (
    camera_info_fields,
    fill_observations,
    transform_matrix,
)
from marker_detector.core.frame_types import FrameOutput, InputError
from marker_detector.detector.conversions import (
    check_message_size,
    fill_fiducials,
    image_from_message,
)
from marker_detector.detector.processor import MarkerProcessor
from marker_detector.detector.settings import (
    PARAMETERS,
    detector_config,
    extrinsics_config,
    search_plan,
)
from slam_core.cli import console_main
from slam_core.errors import ParameterError
from slam_core.images import ImageError, ImageTooLargeError
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
"""Images held for a camera_info or camera mount span at most this much stamp time, s."""

HOLD_MAX_BYTES = 64 * 2**20
"""And at most this many image bytes."""


class DetectorBehaviour(Node):
    """marker_detector's behaviour, shared by the plain and the lifecycle node."""

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
            nothing = LandmarkObservationArray()  # says how far the detector has got
            nothing.header.stamp = message.header.stamp
            nothing.header.frame_id = self.processor.extrinsics.base_frame
            self.observations_publisher.publish(nothing)
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
        # empty too: it tells odometry_ingest how far the detector has got
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
        """The counts on /diagnostics."""
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
