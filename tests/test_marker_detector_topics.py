"""Topic-level: rendered office camera images through the marker_detector node (real rclpy).

Frames of the simulated office run (slam_sim's renderer: AprilTag 36h11 markers on walls and
desks, lens distortion, lighting, blur, noise, JPEG) are published as CompressedImage with
their camera_info and the camera mount on /tf_static; the node's landmark_observations are
compared with the ground truth (marker ids, range and bearing in base_link). Then bad inputs:
images before any camera_info of a fresh node (held, the oldest dropped past HOLD_S,
detected once it comes) and before the camera mount (held until it comes), an unsupported
encoding, an empty and a corrupt image, and a refused marker size; the node logs each and
keeps working.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np
import pytest
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from tf2_msgs.msg import TFMessage

from marker_detector.detector.node import HOLD_S, MarkerDetectorNode
from slam_core.geometry.se3 import OPTICAL_IN_LINK
from slam_core.stamps import ns_to_stamp, stamp_to_ns
from slam_interfaces.msg import FiducialArray, LandmarkObservationArray
from slam_ros.qos import latched_qos
from slam_ros.testing.harness import RosHarness, wait_until
from slam_sim.core.office import simulate_office
from slam_sim.core.office_view import SceneStyle
from slam_sim.office_camera_bag import (
    CAMERA_FORWARD_M,
    CAMERA_HEIGHT_M,
    CameraFrame,
    CameraRig,
    render_frames,
)

pytestmark = pytest.mark.topic

SEED = 3
NUM_FRAMES = 40
MIN_SIDE_PX = 30.0
OPTICAL = 'camera_optical_frame'


def rendered_frames() -> list[CameraFrame]:
    run = simulate_office(SEED, 'standard')
    frames: Iterator[CameraFrame] = render_frames(run, CameraRig(), end_ns=int(12e9))
    return [frame for _, frame in zip(range(NUM_FRAMES), frames, strict=False)]


def camera_info(rig: CameraRig) -> CameraInfo:
    fields = rig.camera.camera_info()
    info = CameraInfo()
    info.header.frame_id = OPTICAL
    info.width, info.height = fields.width, fields.height
    info.distortion_model = fields.distortion_model
    info.d = [float(v) for v in fields.d]
    info.k = [float(v) for v in fields.k]
    info.r = [float(v) for v in fields.r]
    info.p = [float(v) for v in fields.p]
    return info


def tf_static() -> TFMessage:
    from geometry_msgs.msg import TransformStamped
    from scipy.spatial.transform import Rotation

    link = TransformStamped()
    link.header.frame_id, link.child_frame_id = 'base_link', 'camera_link'
    link.transform.translation.x, link.transform.translation.z = CAMERA_FORWARD_M, CAMERA_HEIGHT_M
    link.transform.rotation.w = 1.0
    optical = TransformStamped()
    optical.header.frame_id, optical.child_frame_id = 'camera_link', OPTICAL
    x, y, z, w = Rotation.from_euler('xyz', [-math.pi / 2, 0.0, -math.pi / 2]).as_quat()
    optical.transform.rotation.x, optical.transform.rotation.y = float(x), float(y)
    optical.transform.rotation.z, optical.transform.rotation.w = float(z), float(w)
    return TFMessage(transforms=[link, optical])


def compressed(frame: CameraFrame, stamp_ns: int) -> CompressedImage:
    ok, data = cv2.imencode('.jpg', frame.image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    message = CompressedImage(format='jpeg', data=data.tobytes())
    ns_to_stamp(stamp_ns, message.header.stamp)
    message.header.frame_id = OPTICAL
    return message


def truth_in_base(frame: CameraFrame) -> dict[int, tuple[float, float, float]]:
    """id -> (range m, bearing rad, side px; 0 unless fully visible) of the markers in front
    of the camera, in base_link."""
    truth = frame.truth
    result = {}
    for k in range(len(truth.ids)):
        centre = OPTICAL_IN_LINK @ truth.translation_m[k] + [
            CAMERA_FORWARD_M,
            0.0,
            CAMERA_HEIGHT_M,
        ]
        result[int(truth.ids[k])] = (
            math.hypot(centre[0], centre[1]),
            math.atan2(centre[1], centre[0]),
            float(truth.side_px[k]) if truth.visible[k] else 0.0,
        )
    return result


@pytest.fixture(scope='module')
def frames() -> list[CameraFrame]:
    return rendered_frames()


def make_node(**overrides: object) -> MarkerDetectorNode:
    parameters = {
        'image_transport': 'compressed',
        'marker_size_m': SceneStyle().side_m,
        **overrides,
    }
    return MarkerDetectorNode(
        parameter_overrides=[Parameter(name, value=value) for name, value in parameters.items()]
    )


def test_observations_match_the_rendered_ground_truth(
    ros_harness: RosHarness, frames: list[CameraFrame]
) -> None:
    node = ros_harness.add_node(make_node())
    observations = ros_harness.collect('landmark_observations', LandmarkObservationArray)
    fiducials = ros_harness.collect('fiducials', FiducialArray)
    tf = ros_harness.publisher('/tf_static', TFMessage, latched_qos(depth=10))
    tf.publish(tf_static())
    info = ros_harness.publisher('camera/camera_info', CameraInfo)
    images = ros_harness.publisher('camera/image_raw/compressed', CompressedImage)
    ros_harness.wait_for_subscribers(images)
    ros_harness.wait_for_subscribers(info)
    rig = CameraRig()
    info.publish(camera_info(rig))
    wait_until(lambda: node.processor.camera is not None, what='the camera_info to arrive')
    for index, frame in enumerate(frames):
        stamp_ns = 1_000_000_000 + index * 100_000_000
        images.publish(compressed(frame, stamp_ns))
        # one image at a time: the node's input queue is a best-effort sensor queue
        wait_until(lambda i=index: len(fiducials) > i, what=f'the fiducials of image {index}')
    by_stamp = {
        m.header.stamp.sec * 10**9 + m.header.stamp.nanosec: m for m in observations.messages
    }
    assert all(m.header.frame_id == 'base_link' for m in observations.messages)
    expected = found = 0
    range_errors, bearing_errors = [], []
    for index, frame in enumerate(frames):
        truth = truth_in_base(frame)
        message = by_stamp.get(1_000_000_000 + index * 100_000_000)
        seen = {o.landmark_id: o for o in message.observations} if message else {}
        assert set(seen) <= set(truth), f'image {index}: wrong ids {set(seen) - set(truth)}'
        big = {i for i, (_, _, side) in truth.items() if side >= MIN_SIDE_PX}
        expected += len(big)
        found += len(big & set(seen))
        for landmark_id, observation in seen.items():
            true_range, true_bearing, _ = truth[landmark_id]
            range_errors.append(abs(observation.range_m - true_range) / true_range)
            bearing_errors.append(abs(observation.bearing_rad - true_bearing))
            cov = np.reshape(observation.covariance, (2, 2))
            assert cov[0, 0] > 0 and cov[1, 1] > 0 and np.allclose(cov, cov.T)
    assert expected > 40, 'the frames should show markers'
    assert found / expected >= 0.95
    assert np.median(range_errors) < 0.01
    assert np.degrees(np.median(bearing_errors)) < 0.5
    detections = [d for m in fiducials.messages for d in m.detections]
    assert all(d.dictionary == 'DICT_APRILTAG_36h11' for d in detections)
    assert all(d.marker_size_m == pytest.approx(SceneStyle().side_m) for d in detections)
    assert node.dropped == 0


def compressed_node(
    harness: RosHarness, **overrides: object
) -> tuple[MarkerDetectorNode, Any, Any, Any]:
    """A detector on compressed images that has its camera_info; its fiducials and
    landmark_observations collected, and an image publisher it has matched."""
    node = harness.add_node(make_node(**overrides))
    fiducials = harness.collect('fiducials', FiducialArray)
    observations = harness.collect('landmark_observations', LandmarkObservationArray)
    info = harness.publisher('camera/camera_info', CameraInfo)
    images = harness.publisher('camera/image_raw/compressed', CompressedImage)
    harness.wait_for_subscribers(images)
    harness.wait_for_subscribers(info)
    info.publish(camera_info(CameraRig()))
    wait_until(lambda: node.processor.camera is not None, what='the camera_info to arrive')
    return node, fiducials, observations, images


def test_images_before_the_camera_mount_are_held_until_it_comes(
    ros_harness: RosHarness, frames: list[CameraFrame]
) -> None:
    """Live, the mount's publisher and the camera start together and discovery takes a
    second or two: images that come before the mount are held, not dropped."""
    node, fiducials, observations, images = compressed_node(ros_harness)
    shown = [f for f in frames if np.sum(f.truth.visible & (f.truth.side_px > 40)) >= 1][:3]
    for index, frame in enumerate(shown):
        images.publish(compressed(frame, 1_000_000_000 + index * 100_000_000))
        wait_until(lambda n=index + 1: len(node.held) == n, what=f'image {index} to be held')
    assert not fiducials.messages and node.dropped == 0
    tf = ros_harness.publisher('/tf_static', TFMessage, latched_qos(depth=10))
    tf.publish(tf_static())
    wait_until(lambda: len(fiducials) == len(shown), what='the held images to be detected')
    assert not node.held and node.dropped == 0 and node.images == len(shown)
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in fiducials.messages]
    assert stamps == sorted(stamps)  # in order
    wait_until(lambda: len(observations) == len(shown), what='their observations')


def raw_image_node(harness: RosHarness) -> tuple[MarkerDetectorNode, Any, Any, Any]:
    """A detector on raw images with the mount as parameters; its fiducials collected, and
    image and camera_info publishers it has matched."""
    node = harness.add_node(
        make_node(
            image_transport='raw',
            extrinsics_source='parameters',
            camera_xyz_m=[CAMERA_FORWARD_M, 0.0, CAMERA_HEIGHT_M],
        )
    )
    fiducials = harness.collect('fiducials', FiducialArray)
    images = harness.publisher('camera/image_raw', Image)
    info = harness.publisher('camera/camera_info', CameraInfo)
    harness.wait_for_subscribers(images)
    harness.wait_for_subscribers(info)
    return node, fiducials, images, info


def test_bad_inputs_are_logged_and_the_node_keeps_working(
    ros_harness: RosHarness, frames: list[CameraFrame]
) -> None:
    node, fiducials, images, info = raw_image_node(ros_harness)
    frame = next(f for f in frames if np.sum(f.truth.visible & (f.truth.side_px > 40)) >= 2)

    def raw(encoding: str, data: bytes, width: int, height: int, step: int) -> Image:
        message = Image(encoding=encoding, width=width, height=height, step=step, data=data)
        message.header.frame_id = OPTICAL
        return message

    height, width = frame.image.shape
    good = raw('mono8', frame.image.tobytes(), width, height, width)
    # before any camera_info: held (those of the last HOLD_S seconds), then detected once it
    # comes; one image a second, so the first two are dropped
    kept = int(HOLD_S) + 1
    for number in range(1, kept + 3):
        good.header.stamp.sec = number
        images.publish(good)
        held, dropped = min(number, kept), max(number - kept, 0)
        wait_until(
            lambda h=held, d=dropped: len(node.held) == h and node.dropped == d,
            what=f'image {number} to be held',
        )
    assert node.dropped == 2 and not fiducials.messages
    info.publish(camera_info(CameraRig()))
    wait_until(lambda: len(fiducials) == kept, what='fiducials of the held images')
    assert not node.held and node.dropped == 2
    assert [m.header.stamp.sec for m in fiducials.messages] == list(range(3, kept + 3))
    assert all(len(m.detections) >= 2 for m in fiducials.messages)
    bad = [
        raw('yuv422', bytes(width * height * 2), width, height, width * 2),
        raw('mono8', b'', 0, 0, 0),
        raw('mono8', frame.image.tobytes()[: width * 10], width, height, width),
    ]
    for number, message in enumerate(bad, start=3):
        images.publish(message)
        wait_until(lambda n=number: node.dropped == n, what=f'bad image {number} to be dropped')
    images.publish(good)
    wait_until(lambda: len(fiducials) > kept, what='fiducials after the bad images')
    assert len(fiducials.messages[-1].detections) >= 2

    refused = node.set_parameters([Parameter('marker_size_m', value=-0.3)])
    assert not refused[0].successful and 'marker' in refused[0].reason
    refused = node.set_parameters([Parameter('marker_sizes_m', value=['5:0.0'])])
    assert not refused[0].successful
    accepted = node.set_parameters([Parameter('marker_size_m', value=0.6)])
    assert accepted[0].successful
    images.publish(good)
    wait_until(lambda: len(fiducials) > kept + 1, what='fiducials after the size change')
    before = {d.id: d.pose.position.z for d in fiducials.messages[-2].detections}
    after = {d.id: d.pose.position.z for d in fiducials.messages[-1].detections}
    assert before.keys() & after.keys(), 'the same markers should be detected again'
    for marker_id in before.keys() & after.keys():
        assert after[marker_id] == pytest.approx(2.0 * before[marker_id], rel=1e-6)


def test_an_oversized_image_and_a_bad_camera_info_are_refused_and_counted(
    ros_harness: RosHarness, frames: list[CameraFrame]
) -> None:
    """An 8000x8000 mono8 image (64 MB) is refused before it is copied or decoded, a
    camera_info with fx = 0 is refused and the camera kept; both are counted and the next
    good image is detected."""
    node, fiducials, images, info = raw_image_node(ros_harness)
    good_info = camera_info(CameraRig())
    info.publish(good_info)
    wait_until(lambda: node.processor.camera is not None, what='the camera_info to arrive')
    bad_info = camera_info(CameraRig())
    bad_info.k = [0.0, *good_info.k[1:]]
    info.publish(bad_info)
    wait_until(lambda: node.camera_info_rejected == 1, what='the camera_info with fx = 0')
    assert node.processor.camera is not None and node.processor.camera.K[0, 0] > 0
    huge = Image(encoding='mono8', width=8000, height=8000, step=8000, data=bytes(8000 * 8000))
    huge.header.frame_id = OPTICAL
    images.publish(huge)
    wait_until(lambda: node.too_large == 1, what='the 8000x8000 image refused', timeout_s=30.0)
    frame = next(f for f in frames if np.sum(f.truth.visible & (f.truth.side_px > 40)) >= 2)
    height, width = frame.image.shape
    good = Image(
        encoding='mono8', width=width, height=height, step=width, data=frame.image.tobytes()
    )
    good.header.frame_id = OPTICAL
    good.header.stamp.sec = 2
    images.publish(good)
    wait_until(lambda: len(fiducials) == 1, what='the fiducials of the next good image')
    assert len(fiducials.messages[0].detections) >= 2
    counts = node._counts()
    assert counts['refused too large'] == 1 and counts['camera_info rejected'] == 1
    assert counts['dropped'] == 1 and counts['processed'] == 1


def test_with_detect_every_n_frames_the_images_between_get_empty_fiducials(
    ros_harness: RosHarness, frames: list[CameraFrame]
) -> None:
    """detect_every_n_frames 3: the first image and every third are searched; the others
    are not decoded, get a header-only fiducials message (a node pairing per image does not
    wait) and an empty observations array (odometry_ingest reads how far the detector got),
    and are counted 'not searched'. The last three images carry
    no frame: searched or not, their fiducials are in the camera_info's frame."""
    node, fiducials, observations, images = compressed_node(
        ros_harness,
        extrinsics_source='parameters',
        camera_xyz_m=[CAMERA_FORWARD_M, 0.0, CAMERA_HEIGHT_M],
        detect_every_n_frames=3,
    )
    shown = [f for f in frames if np.sum(f.truth.visible & (f.truth.side_px > 40)) >= 1][:6]
    assert len(shown) == 6
    stamps = [2_000_000_000 + index * 100_000_000 for index in range(len(shown))]
    for index, frame in enumerate(shown):
        image = compressed(frame, stamps[index])
        image.header.frame_id = OPTICAL if index < 3 else ''
        images.publish(image)
        wait_until(lambda n=index + 1: len(fiducials) == n, what=f'fiducials of image {index}')
    got = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in fiducials.messages]
    assert got == stamps
    assert [m.header.frame_id for m in fiducials.messages] == [OPTICAL] * 6
    found = [len(m.detections) > 0 for m in fiducials.messages]
    assert found == [True, False, False, True, False, False]
    wait_until(lambda: len(observations) == 6, what='the observations of every image')
    assert [stamp_to_ns(m.header.stamp) for m in observations.messages] == stamps
    assert [len(m.observations) > 0 for m in observations.messages] == found
    assert {m.header.frame_id for m in observations.messages} == {'base_link'}
    counts = node._counts()
    assert counts['not searched'] == 4 and counts['processed'] == 6 and counts['dropped'] == 0
