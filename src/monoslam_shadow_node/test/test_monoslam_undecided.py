"""Features the Shadow filter has not cleared never move MonoSLAM's camera (ROS-free): an
undecided feature that fills the map is on probation (consider updates only), stays on it when
it becomes Euclidean and when nothing trusted is left in view, and leaves it only once the
Shadow filter hands it over as STATIC; and the depth start (``known_points_source='depth'``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_monoslam_probation import CAMERA, CONFIG, GROUP, _observed, _on_probation, _state

from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
from monoslam_shadow_node.monoslam.core.monoslam_ekf import MIN_TRUSTED_POINTS, gated_update
from monoslam_shadow_node.monoslam.core.monoslam_init import depth_start_features
from monoslam_shadow_node.monoslam.core.monoslam_model import R_SLICE
from monoslam_shadow_node.monoslam.core.monoslam_ransac import ransac_update
from monoslam_shadow_node.monoslam.core.monoslam_snapshot import filter_state, restore_filter
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    TRACKING,
    WAITING,
    MonoSlamConfig,
    MonoSlamFrame,
)
from slam_core.camera import CameraModel

MS = 1_000_000
_LATERAL = np.random.default_rng(5).uniform(-1.2, 1.2, (40, 2))
POINTS = np.column_stack([_LATERAL, np.random.default_rng(6).uniform(2, 4, 40)])
"""Static world points in front of a camera at the origin looking along +z."""


def _uncleared(prior):  # type: ignore[no-untyped-def]
    state = _on_probation(prior)
    for feature in state.features:
        feature.cleared = feature.id not in GROUP
    return state


@pytest.mark.parametrize('update', ['ransac', 'gated'])
def test_undecided_features_stay_on_probation_when_nothing_trusted_is_seen(update: str) -> None:
    """Turned away from everything trusted, cleared features on probation leave it (the
    rescue), but undecided ones do not: the camera is not moved by them."""
    rng = np.random.default_rng(3)
    prior = _state(rng)
    observed = _observed(prior, rng)
    seen = {i: p for i, p in observed.items() if i in GROUP or i < MIN_TRUSTED_POINTS - 1}
    state = _uncleared(prior)
    if update == 'ransac':
        outcome = ransac_update(state, CAMERA, seen, [], CONFIG, np.random.default_rng(1))
    else:
        outcome = gated_update(state, CAMERA, seen, [], CONFIG)
    assert all(f.probation for f in state.features if f.id in GROUP)
    assert outcome.counts.probation > 0
    # the same frame with the group cleared: the rescue lets them move the camera
    cleared = _on_probation(prior)
    gated_update(cleared, CAMERA, seen, [], CONFIG)
    moved_cleared = np.abs(cleared.x[R_SLICE] - prior.x[R_SLICE])
    moved = np.abs(state.x[R_SLICE] - prior.x[R_SLICE])
    assert np.max(moved_cleared) > 5 * np.max(moved)


def _frame(index: int, centre: np.ndarray, ids: np.ndarray, depths: bool = False) -> MonoSlamFrame:
    pixels = CAMERA.project(POINTS[ids] - centre)
    z = (POINTS[ids] - centre)[:, 2] if depths else None
    return MonoSlamFrame(index * 33 * MS, ids.astype(np.int64), pixels, depths_m=z)


def _depth_slam(**config: object) -> MonoSlam:
    settings = {
        'known_points_source': 'depth', 'initialize': 'handover', 'target_measured': 60,
        'undecided_probation': True, 'max_new_per_frame': 40, 'depth_start_points': 10,
        'min_new_spacing_px': 0.0,
    }  # fmt: skip
    settings.update(config)
    return MonoSlam(CAMERA, MonoSlamConfig(**settings))  # type: ignore[arg-type]


def test_a_depth_start_defines_the_world_and_maps_the_points_with_their_depth() -> None:
    slam = _depth_slam()
    ids = np.arange(40)
    waiting = slam.process(_frame(0, np.zeros(3), ids))  # no depth: waits
    assert waiting.status == WAITING and 'depth' in waiting.warnings[-1]
    started = slam.process(_frame(1, np.zeros(3), ids, depths=True))
    assert started.status == TRACKING and len(started.added_ids) == 10
    np.testing.assert_allclose(started.centre, 0.0, atol=1e-9)
    points = {p.id: p.position for p in slam.map_points()}
    for i in started.added_ids:
        np.testing.assert_allclose(points[i], POINTS[i], atol=1e-6)
    assert not slam.undecided_ids & set(started.added_ids)  # measured, not undecided


def test_undecided_fills_are_consider_only_until_cleared_and_then_fix_the_camera() -> None:
    """The depth-started map is trusted; the rest fill it undecided, on probation; a handover
    of one of them clears it in place (its depth kept), and it leaves probation once linear."""
    slam = _depth_slam()
    ids = np.arange(40)
    slam.process(_frame(0, np.zeros(3), ids, depths=True))
    centre = np.zeros(3)
    for k in range(1, 40):
        centre = np.array([0.01 * k, 0.0, 0.0])
        slam.process(_frame(k, centre, ids))
    features = {f.id: f for f in slam._state.features}
    undecided = slam.undecided_ids
    assert undecided and all(features[i].probation for i in undecided)
    assert all(not features[i].probation for i in features if i not in undecided)
    chosen = min(undecided)
    before = slam.map_points()
    assert slam.add_handover(chosen, POINTS[chosen], 0.01 * np.eye(3)) is None
    assert chosen not in slam.undecided_ids and features[chosen].cleared
    after = {p.id: p.position for p in slam.map_points()}
    assert {p.id: p.position.tolist() for p in before}[chosen] == after[chosen].tolist()
    for k in range(40, 80):
        centre = np.array([0.01 * k, 0.0, 0.0])
        slam.process(_frame(k, centre, ids))
    feature = next(f for f in slam._state.features if f.id == chosen)
    assert feature.reference is None and not feature.probation  # Euclidean: it fixes the camera


def test_depth_start_features_are_spread_and_skip_missing_depths() -> None:
    camera = CameraModel(
        640, 480, np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), np.zeros(5)
    )
    pixels = np.array([[100.0, 100], [101, 100], [500, 400], [320, 240], [320, 250]])
    depths = np.array([2.0, 2.0, np.nan, 4.0, 0.0])
    start = depth_start_features(camera, np.arange(5) + 10, pixels, depths, 1.425e-3, 10, 20.0)
    assert start.ids.tolist() == [10, 13]  # 11 too close to 10, 12 and 14 without depth
    np.testing.assert_allclose(1.0 / start.rho[1], 4.0)  # on the axis: distance = depth
    sigma_rho = np.sqrt(start.rho_variance[1])
    np.testing.assert_allclose(sigma_rho, 1.425e-3 * 16 / 16)  # sigma_z / z^2 on the axis


def test_a_depth_restart_after_a_loss_keeps_the_world() -> None:
    """Lost (nothing measured for lost_after_frames), the filter starts again from the next
    frame with depths at the last pose it had, not at the origin: the world stays put."""
    slam = _depth_slam(lost_after_frames=2)
    ids = np.arange(40)
    slam.process(_frame(0, np.zeros(3), ids, depths=True))
    for k in range(1, 10):
        result = slam.process(_frame(k, np.array([0.01 * k, 0.0, 0.0]), ids))
    before = result.centre
    assert before is not None and before[0] > 0.05
    empty = np.zeros(0, dtype=np.int64)
    statuses = [slam.process(_frame(k, np.zeros(3), empty)).status for k in range(10, 14)]
    assert 'lost' in statuses
    restarted = slam.process(_frame(14, np.array([0.14, 0.0, 0.0]), ids, depths=True))
    assert restarted.status == TRACKING and restarted.centre is not None
    np.testing.assert_allclose(restarted.centre, before, atol=0.05)


def test_a_snapshot_keeps_which_features_are_cleared_and_reads_older_ones() -> None:
    """filter_state / restore_filter carry 'cleared'; a snapshot written before it existed
    restores a feature not handed over as undecided (as it was then)."""
    slam = _depth_slam()
    ids = np.arange(40)
    slam.process(_frame(0, np.zeros(3), ids, depths=True))
    for k in range(1, 6):
        slam.process(_frame(k, np.array([0.01 * k, 0.0, 0.0]), ids))
    undecided = slam.undecided_ids
    assert undecided
    arrays, meta = filter_state(slam)
    again = _depth_slam()
    restore_filter(again, arrays, json.loads(json.dumps(meta)))
    assert again.undecided_ids == undecided
    for item in meta['features']:
        del item['cleared']
    older = _depth_slam()
    restore_filter(older, arrays, meta)
    handed = {f.id for f in slam._state.features if f.source == 'handover'}
    assert older.undecided_ids == {f.id for f in slam._state.features} - handed
