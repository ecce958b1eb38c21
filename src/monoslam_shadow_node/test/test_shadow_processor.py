"""The shadow_filter's processor without ROS or the simulator: the pose gate (one rule, also
used by the evaluation pipeline), stamp pairing, holding frames for the camera, skipped and
dropped inputs and their counts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from monoslam_shadow_node.conversions import CameraPose, Features
from monoslam_shadow_node.core.shadow_filter import ShadowConfig
from monoslam_shadow_node.notices import LogThrottle, Notice, log_notice
from monoslam_shadow_node.shadow_processor import (
    NO_GATE,
    ShadowProcessor,
    ShadowStep,
    pose_gate_refusal,
)
from slam_core.camera import CameraModel

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320.0], [0, 300.0, 240.0], [0, 0, 1]]), np.zeros(5)
)  # fmt: skip
POINTS = np.array([[-0.5, 0.2, 4.0], [0.3, -0.1, 5.0], [0.6, 0.4, 3.5]])
MS = 1_000_000
COVARIANCE = np.diag([0.02, 0.025, 0.01, 0.005, 0.009, 0.001]) ** 2


def _features(index: int) -> Features:
    """Frame ``index`` (33 ms apart) of a camera moving along x, R_world_camera = I."""
    centre = np.array([0.02 * index, 0.0, 0.0])
    pixels = CAMERA.project(POINTS - centre)
    return Features(index * 33 * MS, 'camera', np.arange(len(POINTS)), pixels)


def _pose(index: int, covariance: np.ndarray | None = None) -> CameraPose:
    centre = np.array([0.02 * index, 0.0, 0.0])
    return CameraPose(index * 33 * MS, 'map', np.eye(3), centre, covariance)


def _steps(outcomes: list) -> list[ShadowStep]:
    return [o for o in outcomes if isinstance(o, ShadowStep)]


def _notices(outcomes: list, kind: str) -> list[Notice]:
    return [o for o in outcomes if isinstance(o, Notice) and o.kind == kind]


# --- the pose gate --------------------------------------------------------------------------


def test_the_pose_gate_compares_the_largest_standard_deviations() -> None:
    gate = (0.03, 0.01)
    assert pose_gate_refusal(COVARIANCE, gate) is None
    assert pose_gate_refusal(None, gate) is None  # a known pose
    wide = COVARIANCE.copy()
    wide[1, 1] = 0.04**2
    assert pose_gate_refusal(wide, gate) == (
        'position sigma 0.04 m > max_pose_position_sigma_m (0.03)'
    )
    turned = COVARIANCE.copy()
    turned[5, 5] = 0.02**2
    assert pose_gate_refusal(turned, gate) == (
        'rotation sigma 0.02 rad > max_pose_rotation_sigma_rad (0.01)'
    )
    assert pose_gate_refusal(wide, NO_GATE) is None


@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf])
def test_a_covariance_that_is_not_finite_fails_the_gate_even_without_one(bad: float) -> None:
    covariance = COVARIANCE.copy()
    covariance[4, 4] = bad
    assert pose_gate_refusal(covariance, NO_GATE) == 'pose covariance not finite'
    assert pose_gate_refusal(covariance, (0.03, 0.01)) == 'pose covariance not finite'


def test_gated_frames_are_counted_and_never_reach_the_filter() -> None:
    processor = ShadowProcessor(ShadowConfig(), max_pose_sigma=(0.03, 0.01))
    processor.set_camera(CAMERA)
    wide = COVARIANCE.copy()
    wide[0, 0] = 1.0
    nan = np.full((6, 6), math.nan)
    outcomes = []
    for index, covariance in enumerate((COVARIANCE, wide, nan, None)):
        outcomes += processor.add_features(_features(index))
        outcomes += processor.add_pose(_pose(index, covariance))
    steps = _steps(outcomes)
    assert [s.result.stamp_ns for s in steps] == [0, 3 * 33 * MS]
    assert all(s.frame_id == 'map' for s in steps)
    gated = _notices(outcomes, 'pose_gate')
    assert [n.level for n in gated] == ['debug', 'debug']
    assert gated[1].text.endswith('skipped by the pose gate: pose covariance not finite')
    counts = processor.counts
    assert (counts.processed, counts.pose_gated, counts.skipped) == (2, 2, 0)
    assert (counts.features_received, counts.poses_received) == (4, 4)
    assert 'over the pose gate' in processor.status_line()


def test_invalid_pose_gates_are_refused() -> None:
    with pytest.raises(ValueError, match='max_pose_sigma'):
        ShadowProcessor(ShadowConfig(), max_pose_sigma=(0.0, 0.01))


# --- pairing and bad inputs -----------------------------------------------------------------


def test_frames_wait_for_the_camera_and_come_out_in_stamp_order() -> None:
    processor = ShadowProcessor(ShadowConfig())
    outcomes = processor.add_pose(_pose(1)) + processor.add_features(_features(1))
    outcomes += processor.add_features(_features(0)) + processor.add_pose(_pose(0))
    assert not _steps(outcomes) and processor.waiting_features == 2
    waiting = _notices(outcomes, 'no_camera')
    assert waiting and all(n.throttle for n in waiting)
    assert 'holding 2 feature frame(s)' in waiting[-1].text
    steps = _steps(processor.set_camera(CAMERA))
    assert [s.result.stamp_ns for s in steps] == [0, 33 * MS]
    assert processor.counts.processed == 2 and processor.counts.held_pending == len(POINTS)


def test_a_frame_without_pose_is_dropped_and_named() -> None:
    processor = ShadowProcessor(ShadowConfig(), sync_horizon_ns=100 * MS)
    processor.set_camera(CAMERA)
    outcomes = processor.add_features(_features(0)) + processor.add_features(_features(5))
    (never,) = _notices(outcomes, 'no_pose_yet')  # no pose at all yet: a throttled line
    assert never.throttle and 'no camera pose received on monoslam/pose at all yet' in never.text
    outcomes = processor.add_pose(_pose(5)) + processor.add_features(_features(6))
    outcomes += processor.flush()
    (dropped,) = _notices(outcomes, 'dropped')
    assert dropped.stamp_ns == 6 * 33 * MS and 'no camera pose' in dropped.text
    assert processor.counts.dropped == {'no_pose': 2}
    assert processor.counts.processed == 1


def test_a_pose_the_core_refuses_skips_the_frame_with_its_reason() -> None:
    processor = ShadowProcessor(ShadowConfig())
    processor.set_camera(CAMERA)
    bad = CameraPose(0, 'map', np.eye(3), np.array([0.0, math.nan, 0.0]), None)
    outcomes = processor.add_pose(bad) + processor.add_features(_features(0))
    (skipped,) = _notices(outcomes, 'skipped')
    assert skipped.level == 'error' and skipped.text.startswith('frame at stamp 0 ns skipped:')
    assert processor.counts.skipped == 1 and processor.counts.processed == 0
    with pytest.raises(ValueError, match='finite'):
        processor.process(_features(1), CameraPose(33 * MS, 'map', np.eye(3), bad.centre, None))


def test_process_needs_the_camera() -> None:
    with pytest.raises(ValueError, match='no camera yet'):
        ShadowProcessor(ShadowConfig()).process(_features(0), _pose(0))


def test_nan_pixels_are_bad_input_and_the_rest_is_processed() -> None:
    processor = ShadowProcessor(ShadowConfig())
    processor.set_camera(CAMERA)
    features = _features(0)
    pixels = features.pixels.copy()
    pixels[0, 0] = math.nan
    nan = Features(features.stamp_ns, 'camera', features.ids, pixels)
    outcomes = processor.add_features(nan) + processor.add_pose(_pose(0))
    assert [n.level for n in _notices(outcomes, 'input')] == ['warning']
    (step,) = _steps(outcomes)
    assert sorted(t.id for t in step.result.tracks) == [1, 2]


# --- notices --------------------------------------------------------------------------------


def test_throttled_notices_are_throttled_per_kind() -> None:
    throttle = LogThrottle(5.0)
    waiting = Notice('waiting', 'info', 'waiting', throttle=True)
    dropped = Notice('no_pose_yet', 'warning', 'dropping', throttle=True)
    said = Notice('dropped', 'warning', 'dropped')
    assert throttle.allows(waiting, 0.0) and throttle.allows(dropped, 1.0)
    assert not throttle.allows(waiting, 4.9) and throttle.allows(said, 4.9)
    assert throttle.allows(waiting, 5.0)
    with pytest.raises(ValueError, match='notice level'):
        Notice('x', 'fatal', 'x')


class _Logger:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def __getattr__(self, level: str) -> object:
        return lambda text: self.lines.append((level, text))


def test_notices_are_logged_at_their_level_and_throttled() -> None:
    logger, throttle = _Logger(), LogThrottle(5.0)
    for level in ('debug', 'info', 'warning', 'error'):
        log_notice(logger, Notice('x', level, level), throttle, 0.0)
    waiting = Notice('waiting', 'info', 'waiting', throttle=True)
    for now_s in (0.0, 1.0, 6.0):
        log_notice(logger, waiting, throttle, now_s)
    assert logger.lines == [
        ('debug', 'debug'), ('info', 'info'), ('warning', 'warning'), ('error', 'error'),
        ('info', 'waiting'), ('info', 'waiting'),
    ]  # fmt: skip
