"""feature_tracker: camera images in, tracked image features with persistent ids out.

Corners are detected where the image lacks features (Shi-Tomasi or FAST on a grid, subpixel)
and followed by pyramidal Lucas-Kanade with a forward-backward check; each keeps its id while
tracked. With ``use_predictions``, LK starts from SLAM's predicted pixels, and a prediction
with a covariance for a dropped track searches for it (re-identification); an image waits up
to ``prediction_timeout_s`` for its prediction. camera_info is optional (it checks the image
size; a camera change restarts the tracks, ids go on). Bad input is logged and skipped.

Topics:
  subscribes  camera/image_raw (Image) or camera/image_raw/compressed (CompressedImage), per
              image_transport, best effort, 15; camera/camera_info; features/predicted
              (FeatureTrackArray, with use_predictions); with publish_debug_image the
              Shadow filter's statuses (shadow/tracks, shadow/static_features,
              monoslam/revoked)
  publishes   features (FeatureTrackArray, reliable, 10: ids from 1, never reused, raw
              pixels, never NaN), ~/debug_image, /diagnostics
Parameters: ``feature_tracker --help``. In full: docs/design/monoslam_nodes.md.
"""

from __future__ import annotations

import sys
import time
from functools import partial
from typing import Any

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from marker_detector.common.conversions import camera_info_fields
from marker_detector.detector.conversions import check_message_size, image_from_message
from monoslam_shadow_node.common.notices import Notice
from monoslam_shadow_node.feature_tracker.conversions import predictions_from_cdr
from monoslam_shadow_node.feature_tracker.overlay import StatusBook, draw_features
from monoslam_shadow_node.feature_tracker.processor import (
    FeatureFrame,
    FeatureTrackingProcessor,
    Outcome,
    feature_frame_cdr,
    status_line,
)
from monoslam_shadow_node.feature_tracker.settings import (
    NODE_NAME,
    PARAMETERS,
    node_settings,
    tracker_config,
)
from slam_core.cli import console_main
from slam_core.images import ImageError, ImageTooLargeError
from slam_core.stamps import ns_to_stamp, stamp_problem, stamp_to_ns
from slam_interfaces.msg import FeatureTrackArray, ShadowTrackArray
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.qos import SENSOR_DEPTH, output_qos, sensor_qos
from slam_ros.spin import spin_node

IMAGE_TOPIC = 'camera/image_raw'
COMPRESSED_TOPIC = 'camera/image_raw/compressed'
CAMERA_INFO_TOPIC = 'camera/camera_info'
FEATURES_TOPIC = 'features'
PREDICTIONS_TOPIC = 'features/predicted'
DEBUG_IMAGE_TOPIC = '~/debug_image'
STATUS_TOPICS = ('shadow/tracks', 'shadow/static_features', 'monoslam/revoked')
DEBUG_IMAGES_HELD = 3  # decoded images kept until tracked (one may wait for its prediction)
STATUS_PERIOD_S = 10.0
REPEAT_PERIOD_S = 2.0
MIN_POLL_PERIOD_S = 0.001


class KindThrottle:
    """Lets a log line of each kind through at most every ``period_s``, counting those held."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def admit(self, kind: str, now_s: float) -> int | None:
        """Return None to hold the line back, else how many of its kind were held back."""
        last = self._last.get(kind)
        if last is not None and now_s - last < self.period_s:
            self._held[kind] = self._held.get(kind, 0) + 1
            return None
        self._last[kind] = now_s
        return self._held.pop(kind, 0)


class FeatureTrackerNode(Node):
    """Thin adapter around FeatureTrackingProcessor: decode, track, publish."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        values = declare_parameters(self, PARAMETERS)
        self.config = tracker_config(values)
        self.settings = node_settings(values)
        self.processor = FeatureTrackingProcessor(
            self.config,
            use_predictions=self.settings.use_predictions,
            prediction_timeout_s=self.settings.prediction_timeout_s,
            restart_backstep_ns=self.settings.restart_backstep_ns,
            camera_info_topic=CAMERA_INFO_TOPIC,
        )
        self.undecodable = 0
        self.bad_stamps = 0
        self.undecodable_predictions = 0
        self.too_large = 0
        self.busy_s = 0.0
        self._throttle = KindThrottle(REPEAT_PERIOD_S)
        self._status_time, self._status_seen = time.monotonic(), (0, 0, 0)
        self.features_publisher = self.create_publisher(
            FeatureTrackArray, FEATURES_TOPIC, output_qos()
        )
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.diagnostics = Diagnostics(self, self._counts)
        timed = self.diagnostics.timed
        on_image = timed(self._on_image, 'image')
        if self.settings.image_transport == 'raw':
            image_topic = IMAGE_TOPIC
            self.create_subscription(Image, IMAGE_TOPIC, on_image, sensor_qos())
        else:
            image_topic = COMPRESSED_TOPIC
            self.create_subscription(CompressedImage, COMPRESSED_TOPIC, on_image, sensor_qos())
        self.create_subscription(
            CameraInfo, CAMERA_INFO_TOPIC, timed(self._on_camera_info, 'camera_info'), sensor_qos()
        )
        self._poll_timer = None
        if self.settings.use_predictions:
            # taken serialized: predictions_from_cdr reads them from the bytes
            self._deserialize_predictions = partial(
                deserialize_message, message_type=FeatureTrackArray
            )
            self.create_subscription(
                FeatureTrackArray,
                PREDICTIONS_TOPIC,
                timed(self._on_predictions, 'predictions'),
                output_qos(SENSOR_DEPTH),  # one per image, as the images
                raw=True,
            )
            # Runs only while an image waits for its prediction (see _arm_poll).
            self._poll_timer = self.create_timer(
                max(self.settings.prediction_timeout_s / 4, MIN_POLL_PERIOD_S),
                timed(self._poll),
                clock=steady,
            )
            self._poll_timer.cancel()
        self.book = StatusBook()
        self.debug_images = 0
        self._debug_held: dict[int, Any] = {}
        self.debug_publisher = None
        if self.settings.publish_debug_image:
            self.debug_publisher = self.create_publisher(
                Image, DEBUG_IMAGE_TOPIC, output_qos(depth=2)
            )
            for topic in STATUS_TOPICS:
                self.create_subscription(
                    ShadowTrackArray,
                    topic,
                    timed(self._on_statuses, topic.replace('/', '_')),
                    output_qos(depth=100),
                )
        self.create_timer(STATUS_PERIOD_S, self._report_status, clock=steady)
        predictions = (
            f' and predictions on {PREDICTIONS_TOPIC}' if self.settings.use_predictions else ''
        )
        self.get_logger().info(
            f'tracking up to {self.config.max_features} {self.config.detector} features in '
            f'{image_topic}{predictions}; publishing {FEATURES_TOPIC}'
        )

    # --- inputs -----------------------------------------------------------------------------

    def _on_image(self, message: Image | CompressedImage) -> None:
        started = time.perf_counter()
        problem = stamp_problem(message.header.stamp)
        if problem is not None:  # no time: its features could not carry it on
            self.bad_stamps += 1
            self._log(
                Notice('bad_stamp', 'error', f'image dropped: its stamp is not a time, {problem}')
            )
            return
        stamp_ns = stamp_to_ns(message.header.stamp)
        limit = self.settings.max_image_pixels
        try:
            check_message_size(message, limit)
            image = image_from_message(message, limit)
        except ImageTooLargeError as err:
            self.too_large += 1
            if self.too_large == 1:
                self.get_logger().warning(
                    f'image at stamp {stamp_ns} ns refused: {err}; the next ones are only '
                    'counted (refused too large)'
                )
            return
        except ImageError as err:
            self.undecodable += 1
            self._log(
                Notice('undecodable', 'error', f'image at stamp {stamp_ns} ns dropped: {err}')
            )
            return
        if self.debug_publisher is not None and self.debug_publisher.get_subscription_count():
            self._debug_held[stamp_ns] = image
            while len(self._debug_held) > DEBUG_IMAGES_HELD:
                del self._debug_held[min(self._debug_held)]
        self._handle(
            self.processor.add_image(
                stamp_ns, str(message.header.frame_id), image, now_s=time.monotonic()
            )
        )
        self.busy_s += time.perf_counter() - started

    def _on_camera_info(self, message: CameraInfo) -> None:
        notice = self.processor.set_camera_info(**camera_info_fields(message))
        if notice is not None:
            self._log(notice)

    def _on_predictions(self, data: bytes) -> None:
        try:
            predicted, covariances, warps = predictions_from_cdr(
                data, self._deserialize_predictions
            )
        except ValueError as err:  # not what a publisher of the type sends: counted, dropped
            self.undecodable_predictions += 1
            self._log(Notice('undecodable_predictions', 'error', f'prediction dropped: {err}'))
            return
        self._handle(
            self.processor.add_predictions(
                predicted.stamp_ns, predicted.ids, predicted.pixels, covariances, warps
            )
        )

    def _on_statuses(self, message: ShadowTrackArray) -> None:
        self.book.update((int(track.id), int(track.status)) for track in message.tracks)

    def _poll(self) -> None:
        self._handle(self.processor.poll(now_s=time.monotonic()))

    def _arm_poll(self) -> None:
        timer = self._poll_timer
        if timer is None:
            return
        if self.processor.waiting and timer.is_canceled():
            timer.reset()
        elif not self.processor.waiting and not timer.is_canceled():
            timer.cancel()

    # --- outputs ----------------------------------------------------------------------------

    def _handle(self, outcomes: list[Outcome]) -> None:
        for outcome in outcomes:
            if isinstance(outcome, FeatureFrame):
                self.features_publisher.publish(feature_frame_cdr(outcome))
                self._publish_debug_image(outcome)
            else:
                self._log(outcome)
        self._arm_poll()

    def _publish_debug_image(self, frame: FeatureFrame) -> None:
        image = self._debug_held.pop(frame.stamp_ns, None)
        if image is None or self.debug_publisher is None:
            return
        canvas, _ = draw_features(image, frame.features.ids, frame.features.pixels, self.book)
        message = Image()
        ns_to_stamp(frame.stamp_ns, message.header.stamp)
        message.header.frame_id = frame.frame_id
        message.height, message.width = canvas.shape[:2]
        message.encoding = 'bgr8'
        message.step = canvas.shape[1] * 3
        message.data = canvas.tobytes()
        self.debug_publisher.publish(message)
        self.debug_images += 1

    def _log(self, notice: Notice) -> None:
        held = self._throttle.admit(notice.kind, time.monotonic())
        if held is None:
            return
        text = notice.text + (f' ({held} more like this not logged)' if held else '')
        # One call site per severity: rclpy refuses a call site that changes severity.
        if notice.level == 'info':
            self.get_logger().info(text)
        elif notice.level == 'warning':
            self.get_logger().warning(text)
        else:
            self.get_logger().error(text)

    def diagnostics_counts(self) -> dict[str, int]:
        """The counts the node reports on /diagnostics (``_counts``)."""
        return self._counts()

    def _counts(self) -> dict[str, int]:
        """The counts on /diagnostics, by name."""
        stats = self.processor.stats
        return {
            'processed': stats.frames,
            'dropped': sum(stats.images_dropped.values())
            + self.undecodable
            + self.too_large
            + self.bad_stamps
            + self.undecodable_predictions,
            'refused too large': self.too_large,
            'stamps not a time': self.bad_stamps,
            'predictions undecodable': self.undecodable_predictions,
            'camera_info rejected': stats.camera_rejected,
            'restarts': stats.restarts,
            'features': stats.latest_features,
            'tracks started': stats.started,
            're-identified': stats.revived,
            're-identification searches': stats.searched,
            'not searched (too uncertain)': stats.unsearched,
            'candidates left unaligned': stats.unaligned,
            'predictions used': stats.predictions_used,
            'predictions missing': stats.predictions_missed,
            'predictions late': stats.predictions_late,
            'debug images': self.debug_images,
        }

    def _report_status(self) -> None:
        now, frames = time.monotonic(), self.processor.stats.frames
        dropped = sum(self.processor.stats.images_dropped.values())
        seen = (frames, dropped, self.undecodable + self.bad_stamps)
        if seen == self._status_seen:
            return  # nothing came since the last line
        rate = (frames - self._status_seen[0]) / (now - self._status_time)
        self.get_logger().info(self.status_line(rate))
        self._status_time, self._status_seen = now, seen

    def status_line(self, rate_hz: float | None = None) -> str:
        """Return the progress summary: images, features, tracks, drops, time per image."""
        stats = self.processor.stats
        busy = f', {1e3 * self.busy_s / stats.frames:.1f} ms per image' if stats.frames else ''
        undecodable = f', {self.undecodable} undecodable' if self.undecodable else ''
        undecodable += f', {self.bad_stamps} without a time' if self.bad_stamps else ''
        return status_line(stats, rate_hz) + undecodable + busy

    def destroy_node(self) -> None:
        """Log the final summary, then destroy."""
        if self.processor.stats.frames or self.undecodable:
            self.get_logger().info(f'done: {self.status_line()}')
        super().destroy_node()


@console_main(NODE_NAME)
def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C (the Jazzy shutdown pattern)."""
    return spin_node(NODE_NAME, FeatureTrackerNode, argv, parameters=PARAMETERS, doc=__doc__)


if __name__ == '__main__':
    sys.exit(main())
