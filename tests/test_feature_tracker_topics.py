"""Topic-level: synthetic camera images through the feature_tracker node (real rclpy).

The images are a seeded random texture moved by known homographies (a slow pan with a little
rotation, zoom and perspective), 640x480, published one at a time as sensor_msgs/Image
(mono8, bgr8, rgba8) or CompressedImage (PNG) with their camera_info; the node's features
are compared with where the texture says every tracked point is. Then bad inputs to a node
in this process (an empty image, an unsupported encoding, a wrong size, stamps going back
a little, repeating, and a lot), predictions on features/predicted, and a node started as a
process (its log is read back, and it must stop cleanly on SIGINT). Nothing published is
ever NaN.

The node process runs as ``python -m monoslam_shadow_node.feature_tracker.node`` (the same
main() as the installed ``feature_tracker`` executable).
"""

from __future__ import annotations

import math
import signal
import sys
from typing import Any

import cv2
import numpy as np
import pytest
from bag_fixtures import invalid_parameter_error, tool_env
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, STATIC
from monoslam_shadow_node.feature_tracker.node import FeatureTrackerNode
from slam_core.stamps import ns_to_stamp, stamp_to_ns
from slam_interfaces.msg import FeatureTrackArray, ShadowTrack, ShadowTrackArray
from slam_ros.testing.harness import Collector, NodeProcess, RosHarness, wait_until

pytestmark = pytest.mark.topic

WIDTH, HEIGHT = 640, 480
OPTICAL = 'camera_optical_frame'
START_NS = 1_700_000_000 * 10**9
PERIOD_NS = 33_333_333
FRAMES = 12
ACCURACY_PX = 0.3
LOG_TIMEOUT_S = 15.0
MODULE = 'monoslam_shadow_node.feature_tracker.node'


def texture(seed: int) -> np.ndarray:
    noise = np.random.default_rng(seed).uniform(0.0, 255.0, (HEIGHT, WIDTH)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), 2.0)
    return np.clip((smooth - smooth.mean()) / smooth.std() * 45.0 + 128.0, 0.0, 255.0)


def motion(k: int) -> np.ndarray:
    """Texture pixel -> image pixel in frame k."""
    angle, scale = 0.003 * k, 1.0 + 0.004 * k
    cos, sin = scale * math.cos(angle), scale * math.sin(angle)
    return np.array([[cos, -sin, 1.7 * k], [sin, cos, -0.9 * k], [2e-6 * k, 1e-6 * k, 1.0]])


def frame(source: np.ndarray, k: int) -> np.ndarray:
    image = cv2.warpPerspective(
        source, motion(k), (WIDTH, HEIGHT), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
    )
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def moved(homography: np.ndarray, pixel: np.ndarray) -> np.ndarray:
    point = homography @ np.array([pixel[0], pixel[1], 1.0])
    return point[:2] / point[2]


def stamp(k: int) -> int:
    return START_NS + k * PERIOD_NS


def raw_image(gray: np.ndarray, stamp_ns: int, encoding: str = 'mono8') -> Image:
    conversions = {'mono8': None, 'bgr8': cv2.COLOR_GRAY2BGR, 'rgba8': cv2.COLOR_GRAY2RGBA}
    code = conversions[encoding]
    pixels = np.ascontiguousarray(gray if code is None else cv2.cvtColor(gray, code))
    height, width = gray.shape
    message = Image(encoding=encoding, width=width, height=height)
    message.step = pixels.strides[0]
    message.data = pixels.tobytes()
    ns_to_stamp(stamp_ns, message.header.stamp)
    message.header.frame_id = OPTICAL
    return message


def camera_info(width: int = WIDTH, height: int = HEIGHT, fx_px: float = 500.0) -> CameraInfo:
    info = CameraInfo(width=width, height=height, distortion_model='plumb_bob')
    info.header.frame_id = OPTICAL
    info.k = [fx_px, 0.0, width / 2 - 0.5, 0.0, fx_px, height / 2 - 0.5, 0.0, 0.0, 1.0]
    info.d = [0.0] * 5
    return info


def assert_finite(collector: Collector) -> None:
    for message in collector.messages:
        values = [v for t in message.tracks for v in (t.u, t.v)]
        assert all(math.isfinite(v) for v in values), f'NaN or inf on {collector.topic}'


def output(features: Collector, stamp_ns: int) -> Any:
    return features.wait_for(lambda m: stamp_to_ns(m.header.stamp) == stamp_ns)


def node_with(**parameters: object) -> FeatureTrackerNode:
    return FeatureTrackerNode(
        parameter_overrides=[Parameter(name, value=value) for name, value in parameters.items()]
    )


@pytest.fixture(scope='module')
def source() -> np.ndarray:
    return texture(seed=0)


def connected(harness: RosHarness, node: FeatureTrackerNode) -> tuple[Any, Any, Any]:
    """The node's features collected, camera_info and image publishers it has matched, and
    its camera set from a first camera_info."""
    features = harness.collect('features', FeatureTrackArray)
    info = harness.publisher('camera/camera_info', CameraInfo)
    images = harness.publisher('camera/image_raw', Image)
    for publisher in (info, images):
        harness.wait_for_subscribers(publisher)
    info.publish(camera_info())
    wait_until(lambda: node.processor.camera is not None, what='the camera_info to arrive')
    return features, info, images


def test_features_follow_the_true_motion(ros_harness: RosHarness, source: np.ndarray) -> None:
    node = ros_harness.add_node(node_with())
    features, _, images = connected(ros_harness, node)
    encodings = ('mono8', 'bgr8', 'rgba8')
    for k in range(FRAMES):
        images.publish(raw_image(frame(source, k), stamp(k), encodings[k % 3]))
        # one image at a time: the node's image queue is a best-effort sensor queue
        features.wait_for_count(k + 1)

    assert [stamp_to_ns(m.header.stamp) for m in features.messages] == [
        stamp(k) for k in range(FRAMES)
    ]
    assert all(m.header.frame_id == OPTICAL for m in features.messages)
    origin: dict[int, np.ndarray] = {}  # id -> texture pixel where it was first seen
    errors = []
    for k, message in enumerate(features.messages):
        ids = [t.id for t in message.tracks]
        assert ids == sorted(set(ids)) and all(i >= 1 for i in ids)
        for track in message.tracks:
            pixel = np.array([track.u, track.v])
            if track.id in origin:
                errors.append(np.linalg.norm(moved(motion(k), origin[track.id]) - pixel))
            else:
                origin[track.id] = moved(np.linalg.inv(motion(k)), pixel)
    assert len(features.messages[0].tracks) == 150
    assert len(errors) > 1000 and max(errors) < ACCURACY_PX
    first = {t.id for t in features.messages[0].tracks}
    last = {t.id for t in features.messages[-1].tracks}
    assert len(first & last) >= 0.85 * len(first)
    assert_finite(features)
    assert node.processor.stats.frames == FRAMES and node.undecodable == 0


def test_compressed_images_are_tracked_too(ros_harness: RosHarness, source: np.ndarray) -> None:
    ros_harness.add_node(node_with(image_transport='compressed', max_features=60))
    features = ros_harness.collect('features', FeatureTrackArray)
    images = ros_harness.publisher('camera/image_raw/compressed', CompressedImage)
    ros_harness.wait_for_subscribers(images)
    for k in range(3):
        ok, png = cv2.imencode('.png', frame(source, k))
        assert ok
        message = CompressedImage(format='png', data=png.tobytes())
        ns_to_stamp(stamp(k), message.header.stamp)
        message.header.frame_id = OPTICAL
        images.publish(message)
        features.wait_for_count(k + 1)
    first, *_, last = features.messages
    assert len(first.tracks) == 60
    assert len({t.id for t in first.tracks} & {t.id for t in last.tracks}) >= 50


def test_the_debug_image_draws_each_feature_in_its_shadow_filter_status(
    ros_harness: RosHarness, source: np.ndarray
) -> None:
    node = ros_harness.add_node(node_with(publish_debug_image=True, max_features=20))
    features = ros_harness.collect('features', FeatureTrackArray)
    debug = ros_harness.collect('/feature_tracker/debug_image', Image)
    images = ros_harness.publisher('camera/image_raw', Image)
    handed = ros_harness.publisher('shadow/static_features', ShadowTrackArray)
    revoked = ros_harness.publisher('monoslam/revoked', ShadowTrackArray)
    for publisher in (images, handed, revoked):
        ros_harness.wait_for_subscribers(publisher)
    ros_harness.wait_for_publishers('/feature_tracker/debug_image')
    wait_until(lambda: node.debug_publisher.get_subscription_count() > 0, what='a watcher')
    images.publish(raw_image(frame(source, 0), stamp(0)))
    first = [t.id for t in output(features, stamp(0)).tracks]
    static, moving = first[:5], first[5:8]
    handed.publish(ShadowTrackArray(tracks=[ShadowTrack(id=i, status=STATIC) for i in static]))
    revoked.publish(ShadowTrackArray(tracks=[ShadowTrack(id=i, status=DYNAMIC) for i in moving]))
    wait_until(lambda: len(node.book) == 8, what='the statuses to arrive')
    images.publish(raw_image(frame(source, 1), stamp(1)))
    tracks = {t.id: (t.u, t.v) for t in output(features, stamp(1)).tracks}
    drawn = debug.wait_for(lambda m: stamp_to_ns(m.header.stamp) == stamp(1))
    assert drawn.header.frame_id == OPTICAL and drawn.encoding == 'bgr8'
    canvas = np.frombuffer(bytes(drawn.data), np.uint8).reshape(HEIGHT, WIDTH, 3)
    colours = {i: canvas[round(v), round(u)] for i, (u, v) in tracks.items()}
    static, moving = [i for i in static if i in tracks], [i for i in moving if i in tracks]
    assert len(static) >= 3 and moving  # still tracked in the second image
    assert all(colours[i][0] > 200 and colours[i][2] < 60 for i in static)  # blue
    assert all(colours[i][1] > 150 and colours[i][2] < 60 for i in moving)  # green: dynamic
    assert len(debug.messages) == 2 and node._counts()['debug images'] == 2


def test_bad_inputs_drop_images_and_the_node_keeps_tracking(
    ros_harness: RosHarness, source: np.ndarray
) -> None:
    node = ros_harness.add_node(node_with(restart_backstep_s=1.0))
    stats = node.processor.stats
    features = ros_harness.collect('features', FeatureTrackArray)
    info = ros_harness.publisher('camera/camera_info', CameraInfo)
    images = ros_harness.publisher('camera/image_raw', Image)
    for publisher in (info, images):
        ros_harness.wait_for_subscribers(publisher)

    # no camera_info yet: tracked anyway
    images.publish(raw_image(frame(source, 0), stamp(0)))
    first = output(features, stamp(0))
    info.publish(camera_info())
    wait_until(lambda: node.processor.camera is not None, what='the camera_info to arrive')

    def dropped(kind: str, count: int = 1) -> None:
        wait_until(lambda: stats.images_dropped.get(kind, 0) == count, what=f'{kind} drop')

    empty = raw_image(frame(source, 1), stamp(1))
    empty.width = empty.height = empty.step = 0
    empty.data = b''
    images.publish(empty)
    wait_until(lambda: node.undecodable == 1, what='the empty image to be dropped')
    wrong = raw_image(frame(source, 1), stamp(1))
    wrong.encoding = 'yuv422'
    images.publish(wrong)
    wait_until(lambda: node.undecodable == 2, what='the yuv422 image to be dropped')
    images.publish(raw_image(frame(source, 1)[:240, :320], stamp(1)))
    dropped('size_mismatch')
    images.publish(raw_image(frame(source, 1), stamp(1)))
    second = output(features, stamp(1))
    images.publish(raw_image(frame(source, 2), stamp(1) - PERIOD_NS // 2))  # a little back
    dropped('out_of_order')
    images.publish(raw_image(frame(source, 2), stamp(1)))
    dropped('repeated_stamp')
    images.publish(raw_image(frame(source, 2), stamp(2)))
    third = output(features, stamp(2))
    ids = [{t.id for t in m.tracks} for m in (first, second, third)]
    assert len(ids[0] & ids[1] & ids[2]) >= 140  # the bad images did not disturb the tracks

    # the stamps jump 10 s back (the source restarted): new tracks, ids go on
    images.publish(raw_image(frame(source, 3), stamp(3) - 10 * 10**9))
    restarted = output(features, stamp(3) - 10 * 10**9)
    assert min(t.id for t in restarted.tracks) > max(ids[2])
    # a camera change restarts too
    info.publish(camera_info(fx_px=520.0))
    wait_until(lambda: stats.restarts == 2, what='the camera change')
    images.publish(raw_image(frame(source, 4), stamp(4) - 10 * 10**9))
    after_change = output(features, stamp(4) - 10 * 10**9)
    assert min(t.id for t in after_change.tracks) > max(t.id for t in restarted.tracks)

    assert node.undecodable == 2 and stats.frames == 5
    assert stats.images_dropped == {'size_mismatch': 1, 'out_of_order': 1, 'repeated_stamp': 1}
    assert_finite(features)


def test_an_oversized_image_and_a_camera_info_with_fx_0_are_refused_and_counted(
    ros_harness: RosHarness, source: np.ndarray
) -> None:
    """The issue's fault table: camera_info with fx = 0 was taken and every track dropped;
    an 8000x8000 mono8 image (64 MB) is refused before it is copied or decoded."""
    node = ros_harness.add_node(node_with())
    stats = node.processor.stats
    features, info, images = connected(ros_harness, node)
    images.publish(raw_image(frame(source, 0), stamp(0)))
    first = output(features, stamp(0))
    info.publish(camera_info(fx_px=0.0))
    wait_until(lambda: stats.camera_rejected == 1, what='the camera_info with fx = 0 refused')
    assert node.processor.camera is not None and node.processor.camera.k[0] == 500.0
    huge = raw_image(np.zeros((8000, 8000), np.uint8), stamp(1))
    images.publish(huge)
    wait_until(lambda: node.too_large == 1, what='the 8000x8000 image refused', timeout_s=30.0)
    images.publish(raw_image(frame(source, 1), stamp(2)))
    second = output(features, stamp(2))
    kept = {t.id for t in first.tracks} & {t.id for t in second.tracks}
    assert len(kept) >= 140  # neither the camera_info nor the image disturbed the tracks
    counts = node._counts()
    assert counts['refused too large'] == 1 and counts['camera_info rejected'] == 1
    assert counts['dropped'] == 1 and stats.restarts == 0
    assert_finite(features)


def test_predictions_carry_tracks_across_a_jump(
    ros_harness: RosHarness, source: np.ndarray
) -> None:
    """A 60 px jump, beyond two pyramid levels: the image waits for its prediction (it comes
    after the image here) and every track lands where the jump took it."""
    node = ros_harness.add_node(
        node_with(use_predictions=True, prediction_timeout_s=10.0, lk_pyramid_levels=2)
    )
    features = ros_harness.collect('features', FeatureTrackArray)
    images = ros_harness.publisher('camera/image_raw', Image)
    predictions = ros_harness.publisher('features/predicted', FeatureTrackArray)
    for publisher in (images, predictions):
        ros_harness.wait_for_subscribers(publisher)
    jump = np.array([[1.0, 0.0, 60.0], [0.0, 1.0, 20.0], [0.0, 0.0, 1.0]])
    before = frame(source, 0)
    after = cv2.warpPerspective(
        before.astype(np.float32), jump, (WIDTH, HEIGHT), borderMode=cv2.BORDER_REFLECT
    )
    images.publish(raw_image(before, stamp(0)))
    predicted = FeatureTrackArray()
    ns_to_stamp(stamp(0), predicted.header.stamp)
    predictions.publish(predicted)  # an empty prediction releases the first image
    first = output(features, stamp(0))
    images.publish(raw_image(np.clip(np.rint(after), 0, 255).astype(np.uint8), stamp(1)))
    wait_until(lambda: node.processor.waiting, what='the image to wait for its prediction')
    predicted = FeatureTrackArray()
    ns_to_stamp(stamp(1), predicted.header.stamp)
    predicted.tracks = first.tracks
    for track in predicted.tracks:
        track.u, track.v = track.u + 60.0, track.v + 20.0
    truth = {t.id: (t.u, t.v) for t in predicted.tracks}
    predictions.publish(predicted)
    second = output(features, stamp(1))
    kept = [t for t in second.tracks if t.id in truth]
    assert len(kept) >= 100
    assert all(math.dist((t.u, t.v), truth[t.id]) < ACCURACY_PX for t in kept)
    assert node.processor.stats.predictions_used == 2
    assert_finite(features)


def test_a_predicted_search_region_brings_a_dropped_track_back_with_its_id(
    ros_harness: RosHarness, source: np.ndarray
) -> None:
    """View A, an unrelated view (every track dropped), view A again with predictions that
    carry a covariance (FeatureTrack.covariance, as monoslam publishes them): the tracks
    come back under their old ids, where they are."""
    node = ros_harness.add_node(node_with(use_predictions=True, prediction_timeout_s=10.0))
    features = ros_harness.collect('features', FeatureTrackArray)
    images = ros_harness.publisher('camera/image_raw', Image)
    predictions = ros_harness.publisher('features/predicted', FeatureTrackArray)
    for publisher in (images, predictions):
        ros_harness.wait_for_subscribers(publisher)
    view_a = frame(source, 0)
    elsewhere = np.clip(np.rint(texture(seed=9)), 0, 255).astype(np.uint8)
    tracked = []
    for k, image in enumerate((view_a, elsewhere)):
        empty = FeatureTrackArray()
        ns_to_stamp(stamp(k), empty.header.stamp)
        images.publish(raw_image(image, stamp(k)))
        predictions.publish(empty)
        tracked.append(output(features, stamp(k)))
    first, away = tracked
    survivors = {t.id for t in first.tracks} & {t.id for t in away.tracks}
    assert len(survivors) <= 3  # LK found a look-alike for these: not dropped
    images.publish(raw_image(view_a, stamp(2)))
    wait_until(lambda: node.processor.waiting, what='the image to wait for its prediction')
    predicted = FeatureTrackArray()
    ns_to_stamp(stamp(2), predicted.header.stamp)
    predicted.tracks = first.tracks
    for track in predicted.tracks:
        track.u, track.v = track.u + 2.0, track.v - 1.5  # a prediction 2.5 px off
        track.covariance = [9.0, 0.0, 9.0]  # 3 px sigma
    truth = {t.id: (t.u - 2.0, t.v + 1.5) for t in predicted.tracks if t.id not in survivors}
    predictions.publish(predicted)
    back = output(features, stamp(2))
    revived = [t for t in back.tracks if t.id in truth]
    assert len(revived) >= 0.9 * len(truth)
    assert all(math.dist((t.u, t.v), truth[t.id]) < 0.5 for t in revived)
    assert node.processor.stats.revived >= len(revived)  # and survivors dropped, then found
    assert f'{node.processor.stats.revived} dropped tracks re-identified' in node.status_line()
    assert_finite(features)


def test_an_image_whose_prediction_does_not_come_is_tracked_after_the_timeout(
    ros_harness: RosHarness, source: np.ndarray
) -> None:
    node = ros_harness.add_node(node_with(use_predictions=True, prediction_timeout_s=0.05))
    features = ros_harness.collect('features', FeatureTrackArray)
    images = ros_harness.publisher('camera/image_raw', Image)
    ros_harness.wait_for_subscribers(images)
    for k in range(3):
        images.publish(raw_image(frame(source, k), stamp(k)))
        output(features, stamp(k))
    stats = node.processor.stats
    assert stats.predictions_missed == 3 and stats.predictions_used == 0
    first, *_, last = features.messages
    assert len({t.id for t in first.tracks} & {t.id for t in last.tracks}) >= 140


def start_node(harness: RosHarness, *arguments: str) -> NodeProcess:
    command = [sys.executable, '-m', MODULE, '--ros-args', *arguments]
    return harness.start_process('feature_tracker', command, env=tool_env())


def first_contact(images: Any, features: Collector, image: np.ndarray) -> int:
    """Publish ``image`` (stamps stamp(0) + attempt ns) until the node answers; return the
    stamp answered. A best-effort reader drops what comes before it has matched the writer,
    which a node in another process may not have yet when our writer sees it."""
    for attempt in range(100):
        images.publish(raw_image(image, stamp(0) + attempt))
        try:
            answer = features.wait_for(lambda _: True, timeout_s=0.2)
        except TimeoutError:
            continue
        return stamp_to_ns(answer.header.stamp)
    raise TimeoutError('the feature_tracker process never answered an image')


def test_the_node_process_logs_bad_input_and_stops_cleanly(
    ros_harness: RosHarness, source: np.ndarray
) -> None:
    # detection in every image: the image after the bad ones is filled up to max_features
    node = start_node(ros_harness, '-p', 'max_features:=80', '-p', 'detect_every_n_frames:=1')
    features = ros_harness.collect('features', FeatureTrackArray)
    images = ros_harness.publisher('camera/image_raw', Image)
    ros_harness.wait_for_subscribers(images)
    first_contact(images, features, frame(source, 0))
    node.wait_for_line(LOG_TIMEOUT_S, 'no camera/camera_info received yet', 'tracking without it')
    wrong = raw_image(frame(source, 1), stamp(1))
    wrong.encoding = '16UC3'
    images.publish(wrong)
    node.wait_for_line(
        LOG_TIMEOUT_S,
        f'image at stamp {stamp(1)} ns dropped',
        "unsupported image encoding '16UC3'",
    )
    images.publish(raw_image(frame(source, 1), stamp(0) - 1000))
    node.wait_for_line(
        LOG_TIMEOUT_S,
        f'image at stamp {stamp(0) - 1000} ns dropped: it is older than the image before it',
    )
    images.publish(raw_image(frame(source, 1), stamp(1)))
    assert len(output(features, stamp(1)).tracks) == 80
    node.process.send_signal(signal.SIGINT)
    assert node.process.wait(timeout=LOG_TIMEOUT_S) == 0
    assert 'Traceback' not in node.log()
    node.wait_for_line(LOG_TIMEOUT_S, 'done: ', 'images tracked', 'undecodable')
    assert_finite(features)


@pytest.mark.parametrize(
    ('parameter', 'value'),
    [
        ('max_features', '0'),
        ('detector', 'orb'),
        ('fb_threshold_px', '-1.0'),
        ('image_transport', 'theora'),
        ('restart_backstep_s', '0.0'),
    ],
)
def test_invalid_parameter_is_named(parameter: str, value: str) -> None:
    error = invalid_parameter_error([sys.executable, '-m', MODULE], parameter, value)
    assert f'parameter feature_tracker.{parameter}=' in error
    assert error.startswith('feature_tracker: error: ')
