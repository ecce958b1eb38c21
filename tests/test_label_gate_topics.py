"""Topic-level: the label_gate node (real rclpy) passes the features labelled static.

A label masks file with three masks (the left half of the image static, the right half
moving; the second mask all static), and four features frames, one between masks: the
node's features/labelled carries, in order and under each frame's stamp and frame id, only
the tracks on the static half from their first mask on, and never a track once seen on the
moving half; its counts say so. A missing masks file stops the node with an error naming it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rclpy.parameter import Parameter

from slam_core.camera import CameraModel
from slam_core.stamps import ns_to_stamp, stamp_to_ns
from slam_interfaces.msg import FeatureTrack, FeatureTrackArray
from slam_ros.testing.harness import RosHarness, wait_until
from slam_sim.core.depth_labels import MOVING, STATIC, PoseError
from slam_sim.core.label_gate import LabelMasks, write_label_masks
from slam_sim.label_gate_node import LabelGateNode

pytestmark = pytest.mark.topic

STAMPS = 1_548_339_819_874_260_000 + np.array([0, 100, 200], dtype=np.int64) * 1_000_000
CAMERA = CameraModel(60, 40, np.array([[50.0, 0, 30], [0, 50.0, 20], [0, 0, 1]]), np.zeros(5))


def _masks_file(path: Path) -> Path:
    codes = np.full((3, 40, 60), STATIC, dtype=np.int8)
    codes[:, :, 30:] = MOVING
    codes[1] = STATIC
    depth = np.zeros((3, 40, 60), dtype=np.uint16)
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    masks = LabelMasks(STAMPS, codes, depth, poses, CAMERA, PoseError.constant(0.01))
    path.write_bytes(write_label_masks(masks))
    return path


def _frame(stamp_ns: int, tracks: dict[int, tuple[float, float]]) -> FeatureTrackArray:
    message = FeatureTrackArray()
    ns_to_stamp(stamp_ns, message.header.stamp)
    message.header.frame_id = 'camera_optical_frame'
    for track, (u, v) in tracks.items():
        item = FeatureTrack()
        item.id, item.u, item.v = track, u, v
        message.tracks.append(item)
    return message


def test_label_gate_passes_only_the_tracks_labelled_static(
    ros_harness: RosHarness, tmp_path: Path
) -> None:
    path = _masks_file(tmp_path / 'label_masks.npz')
    node = ros_harness.add_node(
        LabelGateNode(parameter_overrides=[Parameter('label_masks_file', value=str(path))])
    )
    labelled = ros_harness.collect('features/labelled', FeatureTrackArray)
    features = ros_harness.publisher('features', FeatureTrackArray)
    ros_harness.wait_for_subscribers(features)
    frames = [
        (int(STAMPS[0]), {1: (5.0, 5.0), 2: (45.0, 5.0)}),
        (int(STAMPS[0]) + 33_000_000, {1: (5.0, 6.0), 2: (45.0, 6.0), 3: (10.0, 10.0)}),
        (int(STAMPS[1]), {1: (5.0, 6.0), 2: (45.0, 6.0), 3: (10.0, 10.0), 4: (50.0, 9.0)}),
        (int(STAMPS[2]), {1: (5.0, 6.0), 2: (5.0, 6.0), 3: (10.0, 10.0), 4: (50.0, 9.0)}),
    ]
    for stamp_ns, tracks in frames:
        features.publish(_frame(stamp_ns, tracks))
    messages = labelled.wait_for_count(len(frames))
    assert [stamp_to_ns(m.header.stamp) for m in messages] == [f[0] for f in frames]
    assert {m.header.frame_id for m in messages} == {'camera_optical_frame'}
    passed = [sorted(t.id for t in m.tracks) for m in messages]
    # 3 has no mask before the second; 2 was seen moving; 4 is labelled moving at the third
    assert passed == [[1], [1], [1, 3, 4], [1, 3]]
    wait_until(lambda: node.gate.frames == len(frames), what='every frame counted')
    assert (node.gate.frames_with_masks, node.gate.features, node.gate.passed) == (3, 13, 7)
    assert node.gate.tracks_moving() == 2


def test_a_missing_masks_file_is_named(ros_harness: RosHarness, tmp_path: Path) -> None:
    missing = tmp_path / 'nowhere.npz'
    with pytest.raises(ValueError, match=r'nowhere\.npz: not a label masks file'):
        LabelGateNode(parameter_overrides=[Parameter('label_masks_file', value=str(missing))])
    with pytest.raises(ValueError, match='label_masks_file is required'):
        LabelGateNode()
