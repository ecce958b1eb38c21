"""The monoslam node's processor without ROS or the simulator: pairing features with target
sightings, the tracking state (waiting, started, lost, re-initialized), the handover intake
and refusal, predictions and the counts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, STATIC
from monoslam_shadow_node.common.core.inputs import Features
from monoslam_shadow_node.common.notices import Notice
from monoslam_shadow_node.monoslam.conversions import HandoverInput, TargetSighting
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    TRACKING,
    WAITING,
    MonoSlamConfig,
    MonoSlamFrame,
)
from monoslam_shadow_node.monoslam.processor import MonoSlamProcessor, MonoSlamStep
from slam_core.camera import CameraModel

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320.0], [0, 300.0, 240.0], [0, 0, 1]]), np.zeros(5)
)  # fmt: skip
HALF_M = 0.08
CORNERS_M = HALF_M * np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=float)
KNOWN = {k: (float(x), float(y), float(z)) for k, (x, y, z) in enumerate(CORNERS_M)}
CENTRE = np.array([0.0, 0.0, -1.0])  # R_world_camera = I: looking along the world z axis
MS = 1_000_000
NO_FEATURES = (np.zeros(0, dtype=np.int64), np.zeros((0, 2)))


def _processor(**config: object) -> MonoSlamProcessor:
    settings = MonoSlamConfig(known_points=KNOWN, initialize='handover', **config)  # type: ignore[arg-type]
    return MonoSlamProcessor(settings, target_text='the test marker', sync_horizon_ns=100 * MS)


def _features(index: int) -> Features:
    return Features(index * 33 * MS, 'camera', *NO_FEATURES)


def _sighting(index: int, seen: bool = True) -> TargetSighting:
    corners = CAMERA.project(CORNERS_M - CENTRE) if seen else None
    return TargetSighting(index * 33 * MS, 'camera', corners, ())


def _steps(outcomes: list) -> list[MonoSlamStep]:
    return [o for o in outcomes if isinstance(o, MonoSlamStep)]


def _kinds(outcomes: list) -> list[str]:
    return [o.kind for o in outcomes if isinstance(o, Notice)]


def test_it_starts_from_the_target_and_then_goes_on_without_fiducials() -> None:
    processor = _processor()
    outcomes = processor.add_features(_features(0))  # no camera yet: held
    assert _kinds(outcomes) == ['no_camera'] and processor.waiting_features == 1
    processor.set_camera(CAMERA)
    outcomes = processor.add_sighting(_sighting(0, seen=False))
    (waiting,) = _steps(outcomes)
    assert waiting.result.status == WAITING and waiting.transition is None
    assert 'no initialization target (the test marker) in view yet' in str(outcomes[-2])
    # before the start a frame whose fiducials never come is dropped
    outcomes = processor.add_features(_features(1)) + processor.add_features(_features(9))
    assert _kinds(outcomes) == ['no_fiducials'] and processor.counts.dropped == {'no_fiducials': 1}
    outcomes = processor.add_sighting(_sighting(9))
    (started,) = _steps(outcomes)
    assert started.transition == 'started' and processor.status == TRACKING
    assert started.pose is not None and np.allclose(started.pose.position, CENTRE, atol=1e-6)
    assert any(o.text.startswith(f'started at stamp {9 * 33 * MS} ns from 4 known points')
               for o in outcomes if isinstance(o, Notice))  # fmt: skip
    # once tracking, a frame whose fiducials never come is processed alone
    outcomes = processor.add_features(_features(10)) + processor.flush()
    (alone,) = _steps(outcomes)
    assert alone.result.status == TRACKING and 'alone' in _kinds(outcomes)
    counts = processor.counts
    assert (counts.processed, counts.alone, counts.features_received) == (3, 1, 4)


def test_tracking_lost_waits_for_the_target_and_re_initializes() -> None:
    processor = _processor(lost_after_frames=2)
    processor.set_camera(CAMERA)
    known = np.arange(4, dtype=np.int64), CAMERA.project(CORNERS_M - CENTRE)
    transitions = []
    for index, keys in enumerate((known, None, None, None, known)):
        frame = MonoSlamFrame(index * 33 * MS, *NO_FEATURES, *(keys or NO_FEATURES))
        step = processor.process_frame(frame)
        transitions.append((step.transition, processor.status))
    assert transitions == [
        ('started', TRACKING), (None, TRACKING), ('lost', WAITING), (None, WAITING),
        ('re-initialized', TRACKING),
    ]  # fmt: skip
    assert processor.counts.lost == 1 and 'lost 1 times' in processor.status_line()


def test_lost_is_said_with_its_reason() -> None:
    processor = _processor(lost_after_frames=1)
    processor.set_camera(CAMERA)
    processor.add_features(_features(0))
    processor.add_sighting(_sighting(0))
    outcomes = processor.add_features(_features(1)) + processor.add_sighting(_sighting(1, False))
    (lost,) = [o for o in outcomes if isinstance(o, Notice) and o.kind == 'lost']
    assert lost.level == 'warning' and lost.text.startswith('tracking lost: no feature')
    assert lost.text.endswith('re-initializing from the target (the test marker) when it is '
                              'seen again')  # fmt: skip


def _handover(feature_id: int, status: int = STATIC, position_m: float = 2.0) -> HandoverInput:
    return HandoverInput(feature_id, status, np.array([0.1, 0.2, position_m]), 1e-4 * np.eye(3))


def test_handovers_are_refused_with_their_reason_and_counted() -> None:
    processor = _processor()
    assert processor.refusal(_handover(1), 'map') == 'handover of feature 1: no camera yet'
    assert processor.owned_ids == frozenset()
    processor.set_camera(CAMERA)
    assert processor.refusal(_handover(2), 'odom') == (
        "handover of feature 2: in frame 'odom', not map_frame 'map'"
    )
    assert processor.refusal(_handover(3, DYNAMIC), 'map') == (
        f'handover of feature 3: status {DYNAMIC}, not STATIC'
    )
    assert 'not finite' in str(processor.refusal(_handover(4, position_m=math.nan), 'map'))
    assert processor.refusal(_handover(5), 'map') is None
    notices = processor.add_handovers([_handover(6), _handover(7, DYNAMIC)], 'map')
    assert [n.text for n in notices] == [f'handover of feature 7: status {DYNAMIC}, not STATIC; '
                                         'refused']  # fmt: skip
    assert (processor.counts.accepted, processor.counts.refused) == (2, 5)


def test_handovers_are_refused_by_a_filter_that_initializes_all() -> None:
    processor = MonoSlamProcessor(MonoSlamConfig(known_points=KNOWN, initialize='all'))
    processor.set_camera(CAMERA)
    assert processor.refusal(_handover(1), 'map') == (
        'handover of feature 1: ignored (initialize=all)'
    )


def test_a_frame_the_core_refuses_is_skipped() -> None:
    processor = _processor()
    processor.set_camera(CAMERA)
    processor.add_features(_features(3))
    processor.add_sighting(_sighting(3))
    outcomes = processor.process(_features(2), _sighting(2))  # before the last frame
    assert _kinds(outcomes) == ['skipped'] and processor.counts.skipped == 1
    assert 'does not advance' in str(outcomes[-1])
    with pytest.raises(ValueError, match='no camera yet'):
        _processor().process_frame(MonoSlamFrame(0, *NO_FEATURES))


def test_predictions_are_due_once_per_later_stamp() -> None:
    processor = _processor()
    assert processor.predictions(0) is None  # no camera
    processor.set_camera(CAMERA)
    processor.add_features(_features(3))
    processor.add_sighting(_sighting(3))
    assert processor.predictions(3 * 33 * MS) is None  # processed already
    ids, pixels, _, _ = processor.predictions(4 * 33 * MS) or (None, None, None, None)
    assert ids is not None and pixels is not None and len(ids) == len(pixels) == 0
    assert processor.predictions(4 * 33 * MS) is None  # once per stamp


def test_a_filter_behind_its_images_sends_empty_predictions_and_catches_up() -> None:
    """Asked for image 5 before image 4 (asked for before it) is processed, the prediction
    would come late: it is empty (a tracker waiting for it goes on) and counted; once the
    image before is processed, the predictions come again."""
    processor = _processor()
    processor.set_camera(CAMERA)
    processor.add_features(_features(3))
    processor.add_sighting(_sighting(3))
    assert processor.predictions(4 * 33 * MS) is not None
    assert (processor.counts.predictions, processor.counts.predictions_behind) == (1, 0)
    behind = processor.predictions(5 * 33 * MS)  # image 4 not processed yet
    assert behind is not None and all(len(part) == 0 for part in behind)
    assert (processor.counts.predictions, processor.counts.predictions_behind) == (1, 1)
    assert processor.predictions(5 * 33 * MS) is None  # once per stamp
    for index in (4, 5):
        processor.add_features(_features(index))
        processor.add_sighting(_sighting(index))
    assert processor.predictions(6 * 33 * MS) is not None
    assert (processor.counts.predictions, processor.counts.predictions_behind) == (2, 1)


def _points_features(index: int, ids: list[int]) -> Features:
    """Features of static points 2-3 m ahead of the camera at CENTRE (ids 1..), raw pixels."""
    rng = np.random.default_rng(7)
    points = np.column_stack([rng.uniform(-0.8, 0.8, (40, 2)), rng.uniform(1.0, 2.0, 40)])
    pixels = CAMERA.project(points[np.array(ids) - 1] - CENTRE)
    return Features(index * 33 * MS, 'camera', np.array(ids, dtype=np.int64), pixels)


def test_undecided_features_fill_the_map_except_those_found_moving() -> None:
    """fill_undecided: without handovers, tracks fill SLAM's map up to max_new_per_frame per
    frame, never one the Shadow filter found DYNAMIC nor one handed over and pending (it
    enters with its handed-over depth)."""
    processor = _processor(max_new_per_frame=40, target_measured=40, min_new_spacing_px=0.0)
    processor.set_camera(CAMERA)
    ids = list(range(1, 41))
    processor.add_features(_points_features(0, ids))
    processor.add_sighting(_sighting(0))
    processor.mark_moving([3, 4])
    assert processor.refusal(_handover(5), 'map') is None
    processor.add_features(_points_features(1, ids))
    steps = _steps(processor.add_sighting(_sighting(1)))
    added = set(steps[-1].result.added_ids)
    assert 5 in added  # the handover, with its depth
    assert not {3, 4} & added
    assert added == set(ids) - {3, 4}
    sources = {p.id: p.source for p in processor.map_points()}
    assert sources[5] == 'handover' and sources[6] == 'new'
    # without filling, only the handover would have entered
    quiet = _processor(fill_undecided=False)
    quiet.set_camera(CAMERA)
    quiet.add_features(_points_features(0, ids))
    quiet.add_sighting(_sighting(0))
    assert quiet.refusal(_handover(5), 'map') is None
    quiet.add_features(_points_features(1, ids))
    assert _steps(quiet.add_sighting(_sighting(1)))[-1].result.added_ids == [5]


def _filling() -> tuple[MonoSlamProcessor, list[int]]:
    """A processor that fills its map with every one of 40 features, after their first
    frame (the target's, where SLAM starts), and the features' ids."""
    processor = _processor(max_new_per_frame=40, target_measured=40, min_new_spacing_px=0.0)
    processor.set_camera(CAMERA)
    ids = list(range(1, 41))
    processor.add_features(_points_features(0, ids))
    processor.add_sighting(_sighting(0))
    return processor, ids


def test_a_filled_feature_the_shadow_filter_finds_dynamic_is_revoked() -> None:
    processor, ids = _filling()
    processor.add_features(_points_features(1, ids))
    processor.add_sighting(_sighting(1))
    slam = processor.slam
    assert slam is not None and {7, 8} <= slam.undecided_ids <= slam.owned_ids
    processor.mark_moving([7, 8])
    assert not {7, 8} & (slam.undecided_ids | slam.owned_ids)
    processor.add_features(_points_features(2, ids))
    step = _steps(processor.add_sighting(_sighting(2)))[-1]
    assert step.result.removed == {7: 'revoked', 8: 'revoked'}
    assert not {7, 8} & set(step.result.added_ids)  # nor do they fill it again


def test_the_status_line_says_where_the_map_came_from() -> None:
    processor, ids = _filling()
    assert processor.refusal(_handover(5), 'map') is None
    processor.add_features(_points_features(1, ids))
    processor.add_sighting(_sighting(1))
    assert '(1 handed over, 39 filled undecided or new)' in processor.status_line()


def test_an_unreadable_input_is_counted_as_dropped_and_said() -> None:
    processor = _processor()
    before = processor.counts.dropped_total
    outcomes = processor.reject('undecodable', 'a features message of 3 bytes is not one')
    assert processor.counts.dropped_total == before + 1
    assert processor.counts.dropped['undecodable'] == 1
    assert [o.text for o in outcomes if isinstance(o, Notice)] == [
        'a features message of 3 bytes is not one'
    ]
