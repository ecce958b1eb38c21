"""apriltag_bridge without ROS: a tag pose in the camera optical frame -> range and bearing in
the base frame through the camera mount, the covariance of marker_detector's sensor model,
the gates, and the queue that waits for the tag transforms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from marker_detector.apriltag_bridge.processor import (
    LOST_NO_CAMERA_INFO,
    LOST_NO_MOUNT,
    LOST_NO_TF,
    AprilTagBridge,
    BridgeConfig,
    Tag,
)
from marker_detector.core.base_frame import to_range_bearing
from marker_detector.core.detection import MarkerDetection, Rejection
from marker_detector.core.pose import marker_object_points, pose_covariance, solve_marker_pose
from marker_detector.core.tag_pose import TagGates, tag_detection
from slam_core.camera import CameraModel

SIZE = 0.3
CAMERA = CameraModel.from_intrinsics(640, 480, (457.0, 457.0), (319.5, 239.5), (-0.1, 0, 0, 0, 0))
OPTICAL = 'camera_optical_frame'
# camera_link in base_link: 0.2 m ahead, 0.1 m left, 0.5 m up, yawed 30 deg to the left
MOUNT_XYZ = (0.2, 0.1, 0.5)
MOUNT_YAW = math.radians(30.0)


def transform(rotation: np.ndarray, translation: object) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, translation
    return matrix


def facing_camera(translation: object, tilt_deg: float = 0.0) -> np.ndarray:
    """A tag pose in the optical frame, OpenCV's marker frame (y up, z towards the camera),
    turned ``tilt_deg`` about its vertical axis."""
    base = Rotation.from_matrix(np.diag([1.0, -1.0, -1.0]))
    turned = base * Rotation.from_euler('y', tilt_deg, degrees=True)
    return transform(turned.as_matrix(), translation)


def corners_at(pose: np.ndarray, size: float = SIZE) -> np.ndarray:
    return CAMERA.project(marker_object_points(size) @ pose[:3, :3].T + pose[:3, 3])


def bridge_with_mount(**config: object) -> AprilTagBridge:
    bridge = AprilTagBridge(BridgeConfig(default_marker_size_m=SIZE, **config))  # type: ignore[arg-type]
    link = transform(Rotation.from_euler('z', MOUNT_YAW).as_matrix(), MOUNT_XYZ)
    optical = transform(Rotation.from_euler('xyz', [-math.pi / 2, 0, -math.pi / 2]).as_matrix(), 0)
    bridge.static.add('base_link', 'camera_link', link)
    bridge.static.add('camera_link', OPTICAL, optical)
    k = CAMERA.K.reshape(9).tolist()
    p = np.hstack([CAMERA.K, np.zeros((3, 1))]).reshape(12).tolist()
    bridge.set_camera_info(OPTICAL, 640, 480, k, list(CAMERA.D), 'plumb_bob', p)
    return bridge


def test_a_tag_in_the_optical_frame_gives_range_and_bearing_through_the_mount() -> None:
    bridge = bridge_with_mount(camera_model='raw')
    x, y, z = 0.3, -0.1, 2.0  # right, down, forward
    pose = facing_camera([x, y, z])
    bridge.add_detections(7, OPTICAL, [Tag('tag36h11', 4, corners_at(pose))], now_s=0.0)
    assert bridge.poll(0.0) == []  # waits for the tag's transform
    bridge.add_transform(OPTICAL, 'tag36h11:4', 7, pose)
    [output] = bridge.poll(0.0)
    # in camera_link: forward z, left -x, up -y; then the mount's yaw and offset, by hand
    forward, left = z, -x
    c, s = math.cos(MOUNT_YAW), math.sin(MOUNT_YAW)
    bx, by = MOUNT_XYZ[0] + c * forward - s * left, MOUNT_XYZ[1] + s * forward + c * left
    [observation] = output.frame.observations
    assert observation.id == 4
    assert observation.range_m == pytest.approx(math.hypot(bx, by), abs=1e-9)
    assert observation.bearing_rad == pytest.approx(math.atan2(by, bx), abs=1e-9)
    assert output.frame.stamp_ns == 7 and output.frame.base_frame == 'base_link'
    assert output.frame.camera_frame == OPTICAL and not output.lost
    assert bridge.counts['observations'] == 1 and bridge.counts['dropped'] == 0


@pytest.mark.parametrize('tilt_deg', [0.0, 35.0])
def test_the_covariance_is_marker_detectors_whatever_the_tag_frame_convention(
    tilt_deg: float,
) -> None:
    pose = facing_camera([-0.4, 0.2, 3.0], tilt_deg)
    corners = corners_at(pose)
    detector = solve_marker_pose(corners, SIZE, CAMERA)
    assert detector is not None
    expected = pose_covariance(detector.jacobian, 0.5)
    # apriltag_ros's PnP frame: y down and z into the tag (a half turn about x)
    flipped = pose.copy()
    flipped[:3, :3] = pose[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    mount = bridge_with_mount().static.lookup('base_link', OPTICAL)
    results = []
    for tag_pose, order in ((pose, [0, 1, 2, 3]), (flipped, [3, 2, 1, 0])):
        detection = tag_detection(
            5, 'tag36h11', corners[order], tag_pose, SIZE, CAMERA, TagGates()
        )
        assert isinstance(detection, MarkerDetection)
        assert detection.reprojection_error_px < 1e-6
        np.testing.assert_allclose(detection.covariance, expected, rtol=1e-6, atol=1e-15)
        results.append(to_range_bearing(detection, mount))
    assert results[0].range_m == pytest.approx(results[1].range_m)
    np.testing.assert_allclose(results[0].covariance, results[1].covariance, rtol=1e-9)
    assert results[0].covariance[0, 0] > 0 and results[0].covariance[1, 1] > 0


def test_the_gates_reject_with_the_reason() -> None:
    gates = TagGates(max_range_m=5.0, max_viewing_angle_rad=math.radians(60.0))
    pose = facing_camera([0.0, 0.0, 2.0])

    def gate_of(tag_pose: np.ndarray, size: float = SIZE, corners: object = None) -> str:
        measured = corners_at(tag_pose) if corners is None else corners
        result = tag_detection(1, 'tag36h11', measured, tag_pose, size, CAMERA, gates)
        return result.gate if isinstance(result, Rejection) else 'accepted'

    assert gate_of(pose) == 'accepted'
    # apriltag_ros was told another size: its pose is twice as far for the same corners
    far = pose.copy()
    far[:3, 3] *= 2.0
    assert gate_of(far, corners=corners_at(pose)) == 'max_reprojection_error_px'
    assert gate_of(facing_camera([0.0, 0.0, 6.0])) == 'max_range_m'
    assert gate_of(facing_camera([0.0, 0.0, 2.0], tilt_deg=70.0)) == 'max_viewing_angle_rad'
    assert gate_of(facing_camera([0.0, 0.0, 30.0])) in ('min_side_px', 'max_range_m')
    assert gate_of(facing_camera([0.0, 0.0, -2.0]), corners=corners_at(pose)) == 'no_pose'
    assert gate_of(np.zeros((4, 4)), corners=corners_at(pose)) == 'no_pose'


def test_rectified_uses_p_and_raw_uses_k_and_d() -> None:
    k = [400.0, 0, 320, 0, 400.0, 240, 0, 0, 1]
    p = [380.0, 0, 300, 0, 0, 381.0, 250, 0, 0, 0, 1, 0]
    d = [-0.2, 0.05, 0, 0, 0]
    rectified = AprilTagBridge(BridgeConfig())
    rectified.set_camera_info(OPTICAL, 640, 480, k, d, 'plumb_bob', p)
    assert rectified.camera is not None
    np.testing.assert_allclose(rectified.camera.K, [[380, 0, 300], [0, 381, 250], [0, 0, 1]])
    assert not np.any(rectified.camera.D)
    raw = AprilTagBridge(BridgeConfig(camera_model='raw'))
    raw.set_camera_info(OPTICAL, 640, 480, k, d, 'plumb_bob', p)
    assert raw.camera is not None
    np.testing.assert_allclose(raw.camera.K.reshape(9), k)
    assert raw.camera.D[0] == -0.2
    with pytest.raises(ValueError, match='p='):
        rectified.set_camera_info(OPTICAL, 640, 480, k, d, 'plumb_bob', [0.0] * 12)


def test_the_queue_waits_in_order_matches_stamps_exactly_and_gives_up_after_two_checks() -> None:
    bridge = bridge_with_mount(tf_wait_s=0.5)
    pose = facing_camera([0.2, 0.0, 2.0])
    corners = corners_at(pose)
    bridge.add_detections(100, OPTICAL, [Tag('tag36h11', 1, corners)], now_s=0.0)
    bridge.add_detections(
        200, OPTICAL, [Tag('tag36h11', 2, corners), Tag('tag36h11', 3, corners)], now_s=0.1
    )
    bridge.add_transform(OPTICAL, 'tag36h11:1', 101, pose)  # another stamp: no match
    bridge.add_transform(OPTICAL, 'tag36h11:2', 200, pose)
    bridge.add_transform(OPTICAL, 'tag36h11:3', 200, pose)
    bridge.add_transform(OPTICAL, 'odom', 100, pose)  # not a tag frame: not kept
    assert 'odom' not in bridge.tags.frames
    assert bridge.poll(0.2, expire=True) == []  # the first waits; the second stays behind it
    assert bridge.poll(0.6, expire=True) == []  # overdue, given up at the next check
    first, second = bridge.poll(0.7, expire=True)
    assert first.frame.stamp_ns == 100 and not first.frame.observations
    [lost] = first.lost
    assert lost.reason == LOST_NO_TF and "'tag36h11:1'" in lost.message
    assert 'nearest transform is +0.0 ms away' in lost.message
    assert [o.id for o in second.frame.observations] == [2, 3]
    assert bridge.counts['dropped'] == 1 and bridge.counts[LOST_NO_TF] == 1
    assert bridge.counts['processed'] == 2 and not bridge.pending


def test_other_families_and_ids_are_counted_and_missing_inputs_named() -> None:
    bridge = AprilTagBridge(BridgeConfig(allowed_ids=(0, 1, 2), default_marker_size_m=SIZE))
    pose = facing_camera([0.2, 0.0, 2.0])
    corners = corners_at(pose)
    warnings = bridge.add_detections(
        5,
        OPTICAL,
        [Tag('tag25h9', 1, corners), Tag('tag36h11', 9, corners), Tag('tag36h11', 1, corners)],
        now_s=0.0,
    )
    assert len(warnings) == 1 and 'tag25h9:1' in warnings[0] and "'tag36h11'" in warnings[0]
    assert bridge.counts['other family'] == 1 and bridge.counts['id not allowed'] == 1
    bridge.add_transform(OPTICAL, 'tag36h11:1', 5, pose)
    assert bridge.poll(1.0, expire=True) == []
    [output] = bridge.poll(1.1, expire=True)
    assert [lost.reason for lost in output.lost] == [LOST_NO_CAMERA_INFO]
    p = [457.0, 0, 320, 0, 0, 457.0, 240, 0, 0, 0, 1, 0]
    bridge.set_camera_info(OPTICAL, 640, 480, [], [], '', p)
    bridge.add_detections(6, OPTICAL, [Tag('tag36h11', 1, corners)], now_s=2.0)
    bridge.add_transform(OPTICAL, 'tag36h11:1', 6, pose)
    bridge.poll(3.0, expire=True)
    [output] = bridge.poll(3.1, expire=True)
    assert [lost.reason for lost in output.lost] == [LOST_NO_MOUNT]
    assert "'base_link'" in output.lost[0].message and 'none yet' in output.lost[0].message
    assert bridge.counts['dropped'] == 2
