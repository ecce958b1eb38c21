"""Topic-level: apriltag_ros's outputs for frames of bags/office_camera.mcap through the real
apriltag_bridge node (real rclpy).

For 40 frames of the simulated office run, the markers the bag's ground truth calls visible
(/ground_truth/fiducials: true corners and pose in camera_optical_frame) are published as
apriltag_ros would: an AprilTagDetectionArray (family tag36h11, corners in another order
than OpenCV's) followed by /tf camera_optical_frame -> tag36h11:<id> in apriltag_ros's
tag frame (y down, z into the tag); the camera mount from the bag's /tf_static and its
camera_info (the corners are raw-image pixels: camera_model 'raw'). The node's
landmark_observations are checked against the truth (the pose is exact, so to 1e-6) and
against what marker_detector's processor makes of the same frames' images (within the
sensor model: the difference under the detector's covariance below the 99 % chi-square
bound, and the covariances alike). Then bad inputs: a tag whose transform never comes and
a tag of another family are counted, reported on /diagnostics, and the node goes on.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from apriltag_msgs.msg import AprilTagDetection, AprilTagDetectionArray, Point
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import TransformStamped
from rclpy.parameter import Parameter
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo
from tf2_msgs.msg import TFMessage

from marker_detector.apriltag_bridge.node import AprilTagBridgeNode
from marker_detector.common.conversions import camera_info_fields, transform_matrix
from marker_detector.detector.conversions import image_from_message
from marker_detector.detector.processor import MarkerProcessor
from marker_detector.detector.settings import PARAMETERS, detector_config, extrinsics_config
from slam_core.geometry.se3 import OPTICAL_IN_LINK
from slam_core.stamps import ns_to_stamp, stamp_to_ns
from slam_interfaces.msg import LandmarkObservationArray
from slam_ros.bag.source import BagSource
from slam_ros.qos import latched_qos
from slam_ros.testing.harness import RosHarness, wait_until
from slam_sim.office_camera_bag import CAMERA_FORWARD_M, CAMERA_HEIGHT_M

pytestmark = pytest.mark.topic

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'office_camera.mcap'
FRAMES = range(0, 400, 10)
SIDE_M = 0.30
CHI2_99 = 9.21  # 99 % quantile of chi-square with 2 degrees of freedom
APRILTAG_AXES = np.diag([1.0, -1.0, -1.0])  # OpenCV's marker frame -> apriltag_ros's


def read_bag() -> dict[str, Any]:
    """The bag's /tf_static, first camera_info, and the images and truths of FRAMES."""
    wanted = set(FRAMES)
    result: dict[str, Any] = {'images': [], 'truths': []}
    counts = {'/camera/image_raw/compressed': 0, '/ground_truth/fiducials': 0}
    with BagSource(BAG) as bag:
        topics = ['/tf_static', '/camera/camera_info', *counts]
        for item in bag.messages(topics):
            message = bag.typestore.deserialize_cdr(item.data, item.msgtype)
            if item.topic == '/tf_static':
                result['tf_static'] = message
            elif item.topic == '/camera/camera_info':
                result.setdefault('camera_info', message)
            else:
                index = counts[item.topic]
                counts[item.topic] += 1
                if index in wanted:
                    key = 'images' if item.topic.startswith('/camera') else 'truths'
                    result[key].append(message)
            if min(counts.values()) > max(FRAMES):
                break
    return result


def detector_observations(data: dict[str, Any]) -> list[dict[int, Any]]:
    """marker_detector's processor on the frames' images: id -> RangeBearing per frame."""
    values = {**PARAMETERS.defaults(), 'marker_size_m': SIDE_M, 'image_transport': 'compressed'}
    processor = MarkerProcessor(detector_config(values), extrinsics_config(values))
    for transform in data['tf_static'].transforms:
        processor.transforms.add(
            transform.header.frame_id, transform.child_frame_id,
            transform_matrix(transform.transform),
        )  # fmt: skip
    processor.set_camera_info(**camera_info_fields(data['camera_info']))
    result = []
    for image in data['images']:
        output = processor.process(
            stamp_to_ns(image.header.stamp), image.header.frame_id, image_from_message(image)
        )
        result.append({o.id: o for o in output.observations})
    return result


def truth_in_base(truth: Any) -> dict[int, tuple[float, float]]:
    """id -> (range m, bearing rad) in base_link of the truth's markers (the mount by hand)."""
    result = {}
    for detection in truth.detections:
        p = detection.pose.position
        centre = OPTICAL_IN_LINK @ [p.x, p.y, p.z] + [CAMERA_FORWARD_M, 0.0, CAMERA_HEIGHT_M]
        result[detection.id] = (math.hypot(centre[0], centre[1]), math.atan2(centre[1], centre[0]))
    return result


def detections_message(stamp_ns: int, tags: list[tuple[str, int, Any]]) -> AprilTagDetectionArray:
    message = AprilTagDetectionArray()
    ns_to_stamp(stamp_ns, message.header.stamp)
    message.header.frame_id = 'camera_optical_frame'
    for family, tag_id, corners in tags:
        points = np.reshape(corners, (4, 2))[::-1]  # another order than OpenCV's
        message.detections.append(
            AprilTagDetection(
                family=family,
                id=tag_id,
                centre=Point(x=float(points[:, 0].mean()), y=float(points[:, 1].mean())),
                corners=[Point(x=float(u), y=float(v)) for u, v in points],
            )
        )
    return message


def tag_transforms(stamp_ns: int, truth: Any) -> TFMessage:
    transforms = []
    for detection in truth.detections:
        item = TransformStamped()
        ns_to_stamp(stamp_ns, item.header.stamp)
        item.header.frame_id, item.child_frame_id = (
            'camera_optical_frame',
            f'tag36h11:{detection.id}',
        )
        q, p = detection.pose.orientation, detection.pose.position
        rotation = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix() @ APRILTAG_AXES
        x, y, z, w = Rotation.from_matrix(rotation).as_quat()
        item.transform.rotation.x, item.transform.rotation.y = float(x), float(y)
        item.transform.rotation.z, item.transform.rotation.w = float(z), float(w)
        item.transform.translation.x, item.transform.translation.y = p.x, p.y
        item.transform.translation.z = p.z
        transforms.append(item)
    return TFMessage(transforms=transforms)


def rclpy_tf_static(message: Any) -> TFMessage:
    transforms = []
    for transform in message.transforms:
        item = TransformStamped()
        item.header.frame_id, item.child_frame_id = (
            transform.header.frame_id,
            transform.child_frame_id,
        )
        t, q = transform.transform.translation, transform.transform.rotation
        item.transform.translation.x, item.transform.translation.y = t.x, t.y
        item.transform.translation.z = t.z
        item.transform.rotation.x, item.transform.rotation.y = q.x, q.y
        item.transform.rotation.z, item.transform.rotation.w = q.z, q.w
        transforms.append(item)
    return TFMessage(transforms=transforms)


def rclpy_camera_info(message: Any) -> CameraInfo:
    info = CameraInfo()
    info.header.frame_id = message.header.frame_id
    info.width, info.height = int(message.width), int(message.height)
    info.distortion_model = message.distortion_model
    info.d = [float(v) for v in message.d]
    info.k = [float(v) for v in message.k]
    info.p = [float(v) for v in message.p]
    return info


@pytest.mark.skipif(not BAG.is_file(), reason=f'{BAG} is not there')
def test_the_bridge_matches_the_detector_and_reports_bad_detections(
    ros_harness: RosHarness,
) -> None:
    data = read_bag()
    assert len(data['images']) == len(data['truths']) == len(FRAMES)
    detector = detector_observations(data)
    overrides = {'marker_size_m': SIDE_M, 'camera_model': 'raw'}
    node = ros_harness.add_node(
        AprilTagBridgeNode(
            parameter_overrides=[Parameter(name, value=value) for name, value in overrides.items()]
        )
    )
    observations = ros_harness.collect('landmark_observations', LandmarkObservationArray)
    diagnostics = ros_harness.collect('/diagnostics', DiagnosticArray)
    ros_harness.publisher('/tf_static', TFMessage, latched_qos(depth=10)).publish(
        rclpy_tf_static(data['tf_static'])
    )
    info = ros_harness.publisher('camera/camera_info', CameraInfo)
    detections = ros_harness.publisher('detections', AprilTagDetectionArray)
    tf = ros_harness.publisher('/tf', TFMessage)
    for publisher in (info, detections, tf):
        ros_harness.wait_for_subscribers(publisher)
    info.publish(rclpy_camera_info(data['camera_info']))
    wait_until(lambda: node.bridge.camera is not None, what='the camera_info to arrive')
    stamps = [stamp_to_ns(image.header.stamp) for image in data['images']]
    for stamp_ns, truth in zip(stamps, data['truths'], strict=True):
        tags = [('tag36h11', d.id, d.corners_px) for d in truth.detections]
        detections.publish(detections_message(stamp_ns, tags))  # first, as apriltag_ros
        tf.publish(tag_transforms(stamp_ns, truth))
    bridge = node.bridge
    wait_until(lambda: bridge.counts['processed'] == len(FRAMES), what='every detection')
    assert bridge.counts['dropped'] == 0, dict(bridge.counts)

    wait_until(lambda: len(observations) == len(FRAMES), what='the observations')
    messages = observations.messages
    assert [stamp_to_ns(m.header.stamp) for m in messages] == stamps  # in order, image stamps
    assert {m.header.frame_id for m in messages} == {'base_link'}
    common, detected, chi2, ratios = 0, 0, [], []
    for message, truth, seen in zip(messages, data['truths'], detector, strict=True):
        bridged = {o.landmark_id: o for o in message.observations}
        expected = truth_in_base(truth)
        assert set(bridged) <= set(expected)
        for tag_id, observation in bridged.items():
            true_range, true_bearing = expected[tag_id]
            assert observation.range_m == pytest.approx(true_range, abs=1e-6)
            assert observation.bearing_rad == pytest.approx(true_bearing, abs=1e-6)
        detected += len(seen)
        for tag_id in set(seen) & set(bridged):
            common += 1
            mine, theirs = bridged[tag_id], seen[tag_id]
            difference = np.array(
                [mine.range_m - theirs.range_m, mine.bearing_rad - theirs.bearing_rad]
            )
            chi2.append(float(difference @ np.linalg.solve(theirs.covariance, difference)))
            ratios.append(
                np.diag(np.reshape(mine.covariance, (2, 2))) / np.diag(theirs.covariance)
            )
    assert common >= 80 and common >= 0.9 * detected, (common, detected)
    assert max(chi2) < CHI2_99, sorted(chi2)[-5:]
    assert np.min(ratios) > 0.8 and np.max(ratios) < 1.25, (np.min(ratios), np.max(ratios))
    assert bridge.counts['observations'] == sum(len(m.observations) for m in messages)

    # bad inputs: a tag whose transform never comes, a tag of another family
    bad_ns, after_ns = stamps[-1] + 10**8, stamps[-1] + 2 * 10**8
    truth = data['truths'][-1]
    corners = truth.detections[0].corners_px
    detections.publish(
        detections_message(bad_ns, [('tag36h11', 500, corners), ('tag25h9', 3, corners)])
    )
    tags = [('tag36h11', d.id, d.corners_px) for d in truth.detections]
    detections.publish(detections_message(after_ns, tags))
    tf.publish(tag_transforms(after_ns, truth))
    wait_until(lambda: len(observations) == len(FRAMES) + 2, what='the frame after the bad one')
    bad, after = observations.messages[-2:]
    # the bad frame's array is empty: it says how far the bridge has got
    assert stamp_to_ns(bad.header.stamp) == bad_ns and not bad.observations
    assert stamp_to_ns(after.header.stamp) == after_ns and after.observations
    assert bridge.counts['dropped no tag tf'] == bridge.counts['dropped'] == 1
    assert bridge.counts['other family'] == 1

    def reported() -> bool:
        for array in diagnostics.messages:
            for status in array.status:
                values = {value.key: value.value for value in status.values}
                if values.get('dropped no tag tf') == '1' and values.get('other family') == '1':
                    return True
        return False

    wait_until(reported, what='/diagnostics to report the dropped tag and the other family')
    levels = [s.level for a in diagnostics.messages for s in a.status]
    assert DiagnosticStatus.WARN in levels, levels  # WARN while it drops
