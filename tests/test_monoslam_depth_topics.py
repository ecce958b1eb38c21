"""Topic-level: monoslam started from a depth image (known_points_source 'depth', real rclpy).

A static scene of 60 points seen by a camera that moves sideways: camera_info, features (the
points' pixels, ids renumbered by a constant between two runs) and 16UC1 depth images (the
points' depths in small patches, every third image, 14 ms after its colour image as an RGB-D
camera stamps them) are published to a monoslam node in this process. Checked on messages:
the node starts at the first image with a depth image, monoslam/pose follows the camera in
the start camera's frame (metres: the depth fixed the scale), frames before the first depth
image are counted as dropped, later depth images as not needed, and a depth image in an
encoding it cannot read is dropped while the node goes on. The run with renumbered ids gives
the same poses.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image

from monoslam_shadow_node.monoslam.node import MonoSlamNode
from slam_core.blas import single_threaded_blas
from slam_core.stamps import ns_to_stamp, stamp_to_ns
from slam_interfaces.msg import FeatureTrack, FeatureTrackArray
from slam_ros.testing.harness import RosHarness, wait_until

pytestmark = pytest.mark.topic

FX, CX, CY = 500.0, 320.0, 240.0
START_NS = 1_548_339_819_874_260_000
PERIOD_NS = 33_333_333
FRAMES = 40
RNG = np.random.default_rng(17)
POINTS = np.column_stack([RNG.uniform(-1.5, 1.5, (60, 2)), RNG.uniform(2.5, 4.0, 60)])


@pytest.fixture(scope='module', autouse=True)
def one_blas_thread() -> None:
    single_threaded_blas()


def _centre(index: int) -> np.ndarray:
    return np.array([0.004 * index, 0.001 * index, 0.0])


def _pixels(index: int) -> np.ndarray:
    local = POINTS - _centre(index)
    u = FX * local[:, 0] / local[:, 2] + CX
    return np.column_stack([u, FX * local[:, 1] / local[:, 2] + CY])


def _camera_info(stamp_ns: int) -> CameraInfo:
    info = CameraInfo()
    ns_to_stamp(stamp_ns, info.header.stamp)
    info.header.frame_id = 'camera_optical_frame'
    info.width, info.height, info.distortion_model = 640, 480, 'plumb_bob'
    info.d = [0.0] * 5
    info.k = [FX, 0.0, CX, 0.0, FX, CY, 0.0, 0.0, 1.0]
    info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    info.p = [FX, 0.0, CX, 0.0, 0.0, FX, CY, 0.0, 0.0, 0.0, 1.0, 0.0]
    return info


def _depth(index: int, stamp_ns: int, encoding: str = '16UC1') -> Image:
    millimetres = np.zeros((480, 640), dtype='<u2')
    local = POINTS - _centre(index)
    for (u, v), z in zip(np.rint(_pixels(index)).astype(int), local[:, 2], strict=True):
        if 4 <= u < 636 and 4 <= v < 476:
            millimetres[v - 4 : v + 5, u - 4 : u + 5] = round(z * 1000)
    image = Image()
    ns_to_stamp(stamp_ns, image.header.stamp)
    image.header.frame_id = 'camera_optical_frame'
    image.height, image.width, image.encoding, image.step = 480, 640, encoding, 1280
    image.data = millimetres.tobytes()
    return image


def _features(index: int, stamp_ns: int, offset: int) -> FeatureTrackArray:
    message = FeatureTrackArray()
    ns_to_stamp(stamp_ns, message.header.stamp)
    message.header.frame_id = 'camera_optical_frame'
    message.tracks = [
        FeatureTrack(id=int(k + offset), u=float(u), v=float(v))
        for k, (u, v) in enumerate(_pixels(index))
    ]
    return message


def _run(tmp_path: Path, offset: int) -> tuple[dict[int, np.ndarray], Any]:
    harness = RosHarness(tmp_path / f'run{offset}')
    try:
        poses = harness.collect('monoslam/pose', PoseWithCovarianceStamped)
        node = MonoSlamNode(
            parameter_overrides=[
                Parameter('known_points_source', value='depth'),
                Parameter('initialize', value='all'),
                Parameter('min_new_spacing_px', value=0.0),
            ]
        )
        harness.add_node(node)
        info = harness.publisher('camera/camera_info', CameraInfo)
        features = harness.publisher('features', FeatureTrackArray)
        depth = harness.publisher('camera/depth/image_raw', Image)
        for publisher in (info, features, depth):
            harness.wait_for_subscribers(publisher)
        sent = 0
        for index in range(FRAMES):
            stamp_ns = START_NS + index * PERIOD_NS
            info.publish(_camera_info(stamp_ns))
            features.publish(_features(index, stamp_ns, offset))
            if index == 2 or (index >= 3 and index % 3 == 0):
                # index 2: one the node cannot read (dropped, the node goes on); paced: the
                # node takes each depth image before the next one is sent
                encoding = 'rgb8' if index == 2 else '16UC1'
                sent += 1
                depth.publish(_depth(index, stamp_ns + 14_000_000, encoding=encoding))
                wait_until(
                    lambda n=sent: node.processor.counts.depth_received == n,
                    timeout_s=10.0, what=f'depth image {sent} received',
                )  # fmt: skip
            # paced: each frame once the one before was processed (or held for its depth)
            wait_until(
                lambda n=index + 1: node.processor.counts.features_received == n,
                timeout_s=10.0, what=f'features frame {index} received',
            )  # fmt: skip
        last_ns = START_NS + (FRAMES - 1) * PERIOD_NS
        poses.wait_for(lambda m: stamp_to_ns(m.header.stamp) == last_ns, timeout_s=20.0)
        counts = node.processor.counts
        return {stamp_to_ns(m.header.stamp): m for m in poses.messages}, counts
    finally:
        harness.close()


def test_monoslam_starts_from_depth_and_tracks_in_metres(
    ros_context: None, tmp_path: Path
) -> None:
    poses, counts = _run(tmp_path, 0)
    first = min(poses)
    assert first == START_NS + 3 * PERIOD_NS  # the first image with a depth image
    assert counts.dropped.get('no_depth', 0) == 3 and counts.dropped.get('bad_depth') == 1
    assert counts.depth_unused >= 10 and counts.lost == 0
    for stamp_ns, message in poses.items():
        index = round((stamp_ns - START_NS) / PERIOD_NS)
        p = message.pose.pose.position
        expected = _centre(index) - _centre(3)
        assert math.dist((p.x, p.y, p.z), expected) < 0.02, (index, p, expected)
    renumbered, _ = _run(tmp_path, 5000)
    assert renumbered.keys() == poses.keys()
    for stamp_ns, message in poses.items():
        a, b = message.pose.pose.position, renumbered[stamp_ns].pose.pose.position
        assert (a.x, a.y, a.z) == pytest.approx((b.x, b.y, b.z), abs=1e-9)
