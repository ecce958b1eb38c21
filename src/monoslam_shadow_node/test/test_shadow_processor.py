"""The shadow_filter's processor without ROS or the simulator: every frame with a usable pose
is processed however uncertain the pose (only a covariance that is not finite is refused; the
evaluation pipeline uses the same processor), stamp pairing, holding frames for the camera,
skipped and dropped inputs and their counts."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from monoslam_shadow_node.common.core.inputs import CameraPose, Features
from monoslam_shadow_node.common.notices import LogThrottle, Notice, log_notice
from monoslam_shadow_node.shadow_filter.core.near_static import WAIT_WARNING
from monoslam_shadow_node.shadow_filter.core.shadow_decision import UNFIT_WARNING
from monoslam_shadow_node.shadow_filter.core.shadow_filter import ShadowConfig
from monoslam_shadow_node.shadow_filter.processor import (
    GATE_WARNING,
    ShadowProcessor,
    ShadowStep,
    pose_covariance_refusal,
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


# --- the pose covariance --------------------------------------------------------------------


@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize('entry', [(4, 4), (0, 5)])
def test_a_pose_covariance_that_is_not_finite_is_refused(
    bad: float, entry: tuple[int, int]
) -> None:
    covariance = COVARIANCE.copy()
    covariance[entry] = bad
    assert pose_covariance_refusal(covariance) == 'pose covariance not finite'
    assert pose_covariance_refusal(COVARIANCE) is None
    assert pose_covariance_refusal(None) is None  # a known pose
    assert pose_covariance_refusal(np.diag([1e2] * 3 + [1.0] * 3)) is None  # size: no limit


def test_every_frame_with_a_usable_pose_is_processed_however_uncertain() -> None:
    processor = ShadowProcessor(ShadowConfig())
    processor.set_camera(CAMERA)
    wide = np.diag([1.0, 1.0, 1.0, 0.3, 0.3, 0.3]) ** 2  # 1 m, 0.3 rad
    nan = np.full((6, 6), math.nan)
    outcomes = []
    for index, covariance in enumerate((COVARIANCE, wide, nan, None)):
        outcomes += processor.add_features(_features(index))
        outcomes += processor.add_pose(_pose(index, covariance))
    steps = _steps(outcomes)
    assert [s.result.stamp_ns for s in steps] == [0, 33 * MS, 3 * 33 * MS]
    assert all(s.frame_id == 'map' for s in steps)
    (refused,) = _notices(outcomes, 'pose_covariance')
    assert refused.level == 'warning' and refused.stamp_ns == 2 * 33 * MS
    assert refused.text.endswith('skipped: pose covariance not finite (pose from monoslam/pose)')
    counts = processor.counts
    assert (counts.processed, counts.pose_refused, counts.skipped) == (3, 1, 0)
    assert (counts.features_received, counts.poses_received) == (4, 4)
    assert '1 with a non-finite pose covariance' in processor.status_line()


def _hand_held_run(covariance: np.ndarray | None, frames: int = 150) -> tuple[int, list[int]]:
    """A hand-held camera (a 3D oscillation of some 0.3 m) sees 20 static points 2.5-5 m away
    (1 px noise), every pose with ``covariance``; return the frames processed and the frame
    of each handover."""
    rng = np.random.default_rng(1)
    points = np.column_stack(
        [rng.uniform(-1.5, 1.5, 20), rng.uniform(-1.0, 1.0, 20), rng.uniform(2.5, 5.0, 20)]
    )
    processor = ShadowProcessor(ShadowConfig())
    processor.set_camera(CAMERA)
    handed = []
    for index in range(frames):
        t = 0.033 * index
        centre = np.array([0.3 * np.sin(t), 0.15 * np.sin(2.0 * t), 0.2 * np.sin(0.7 * t)])
        pixels = CAMERA.project(points - centre) + rng.normal(0.0, 1.0, (20, 2))
        features = Features(index * 33 * MS, 'camera', np.arange(20), pixels)
        outcome = processor.process(
            features, CameraPose(index * 33 * MS, 'map', np.eye(3), centre, covariance)
        )
        assert isinstance(outcome, ShadowStep)
        handed += [index] * len(outcome.result.handovers)
    return processor.counts.processed, handed


def test_a_large_pose_covariance_makes_decisions_slower_never_impossible() -> None:
    """SLAM's pose covariance enters the tests: a pose 0.1 m / 0.03 rad uncertain (3x the
    0.03 m / 0.01 rad above which frames used to be skipped) delays the handovers; it does
    not stop them."""
    known_frames, known = _hand_held_run(None)
    wide = np.diag([0.1] * 3 + [0.03] * 3) ** 2
    uncertain_frames, uncertain = _hand_held_run(wide)
    assert known_frames == uncertain_frames == 150
    assert len(known) >= 15 and len(uncertain) >= 15  # measured 18 and 20 of 20
    assert np.median(uncertain) > 1.5 * np.median(known)  # measured frame 72.5 against 30.5


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


def test_static_fits_put_off_as_too_near_are_counted_and_said() -> None:
    """Nothing silent: a frame whose classifier put off a static fit lying too near a camera
    (near_static), or tested a feature whose views fix no static point, counts it, in the
    status line, apart from the gated measurements."""
    processor = ShadowProcessor(ShadowConfig())
    processor.set_camera(CAMERA)
    (step,) = _steps(processor.add_features(_features(0)) + processor.add_pose(_pose(0)))
    near = (
        f'feature 7: its static fit lies 0.13 m along a ray, {WAIT_WARNING}: waiting for more '
        'views'
    )
    warnings = [near, f'feature 8: {GATE_WARNING}', f'feature 9: {UNFIT_WARNING}']
    notices = processor._warnings(dataclasses.replace(step.result, warnings=warnings))
    assert [n.level for n in notices] == ['debug', 'debug', 'debug']
    assert processor.counts.near_waits == 1 and processor.counts.innovation_gated == 1
    assert processor.counts.unfit == 1
    assert '1 static fits too near a camera put off' in processor.status_line()
    assert '1 tests without a static fit' in processor.status_line()


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
