"""MonoSLAM core on short simulated scenes: the start from known points, tracking, handovers,
loss and restart, predictions and bad frames."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
from monoslam_shadow_node.monoslam.core.monoslam_init import camera_from_known_points
from monoslam_shadow_node.monoslam.core.monoslam_model import CAMERA_SIZE
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    LOST,
    TRACKING,
    WAITING,
    MonoSlamConfig,
    MonoSlamFrame,
    MonoSlamInputError,
)
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import log_rotation
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import simulate_dynamic_scene
from slam_sim.core.init_target import InitTarget, target_pixels

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320.7], [0, 300.0, 238.9], [0, 0, 1]]),
    np.array([-0.05, 0.01, 0.0, 0.0, 0.0]),
)  # fmt: skip


def test_pose_from_known_points_is_exact_without_noise_and_covariance_scales() -> None:
    target = InitTarget()
    run = simulate_dynamic_scene(3, DynamicSceneConfig(duration_s=0.2, static_points=10))
    frame = run.frames[0]
    pixels = target_pixels(target, run.camera, frame.camera_rotation, frame.camera_position)
    assert pixels is not None
    info = run.camera.camera_info()
    camera = CameraModel.from_camera_info(info.width, info.height, info.k, info.d, 'plumb_bob')
    fix = camera_from_known_points(camera, target.corners_m, pixels, 1.0)
    assert fix is not None
    assert np.allclose(fix.centre, frame.camera_position, atol=1e-8)
    assert np.allclose(fix.rotation, frame.camera_rotation, atol=1e-8)
    half = camera_from_known_points(camera, target.corners_m, pixels, 0.5)
    assert half is not None
    assert np.allclose(half.pose_covariance, fix.pose_covariance / 4.0)
    assert camera_from_known_points(camera, target.corners_m[:3], pixels[:3], 1.0) is None


def _frames(run, target, rng, *, static_only: bool):  # type: ignore[no-untyped-def]
    for frame in run.frames:
        pixels = target_pixels(target, run.camera, frame.camera_rotation, frame.camera_position)
        keys = np.arange(4) if pixels is not None else np.zeros(0, np.int64)
        known = np.zeros((0, 2)) if pixels is None else pixels + rng.normal(size=(4, 2))
        keep = ~run.point_moving[frame.point_ids] if static_only else np.ones(
            len(frame.point_ids), bool)  # fmt: skip
        yield frame, MonoSlamFrame(frame.stamp_ns, frame.track_ids[keep], frame.pixels[keep],
                                   keys, known)  # fmt: skip


def _filter(run, initialize: str = 'all', probation: bool = True) -> MonoSlam:  # type: ignore[no-untyped-def]
    """The filter; with initialize='handover', only handovers enter its map (no filling from
    undecided features: these tests follow the handovers they make)."""
    info = run.camera.camera_info()
    camera = CameraModel.from_camera_info(info.width, info.height, info.k, info.d, 'plumb_bob')
    known = {k: tuple(p) for k, p in enumerate(InitTarget().corners_m)}
    config = MonoSlamConfig(
        known_points=known,
        initialize=initialize,
        handover_probation=probation,
        fill_undecided=False,
    )
    return MonoSlam(camera, config)


def test_filter_tracks_static_scene_consistently() -> None:
    run = simulate_dynamic_scene(2, DynamicSceneConfig(duration_s=4.0, objects=0))
    slam = _filter(run)
    nees, rms = _pose_nees(slam, run)
    assert rms < 0.05  # measured ~0.02 m
    assert 2.0 < nees < 15.0  # 6 DoF: 6 expected
    points = slam.map_points()
    assert len(points) > 20
    assert slam.state_size <= CAMERA_SIZE + 6 * slam.config.max_features
    truth = run.point_positions[0]
    euclidean = [p for p in points if p.parametrization == 'euclidean']
    assert euclidean, 'no feature converted to Euclidean'
    distances = [np.linalg.norm(p.position - truth[run.track_point[p.id]]) for p in euclidean]
    assert np.median(distances) < 0.15


def _pose_nees(slam: MonoSlam, run) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    """Return the mean pose NEES and the RMS position error (m) after the first second."""
    errors, nees = [], []
    for frame, measurements in _frames(run, InitTarget(), np.random.default_rng(0),
                                       static_only=True):  # fmt: skip
        result = slam.process(measurements)
        assert result.status == TRACKING
        assert result.centre is not None and result.rotation is not None
        assert result.pose_covariance is not None
        error = np.concatenate([
            result.centre - frame.camera_position,
            log_rotation(result.rotation @ frame.camera_rotation.T),
        ])  # fmt: skip
        errors.append(np.linalg.norm(error[:3]))
        nees.append(error @ np.linalg.solve(result.pose_covariance, error))
    return float(np.mean(nees[30:])), float(np.sqrt(np.mean(np.square(errors[30:]))))


def test_filter_with_tracker_offsets_keeps_them_in_the_state_and_stays_consistent() -> None:
    # 2 px offsets that persist (correlation 1 s): declared, each feature keeps its offset in
    # the state and the pose NEES stays near 6 (measured 5.1); treating the same noise as
    # white (its whole variance per sighting) makes the filter overconfident (measured 53)
    scene = DynamicSceneConfig(duration_s=6.0, objects=0, tracking_offset_px=2.0)
    run = simulate_dynamic_scene(2, scene)
    slam = _filter(run)
    slam.config = dataclasses.replace(
        slam.config, tracking_offset_px=2.0,
        tracking_offset_time_s=scene.tracking_correlation_time_s,
    )  # fmt: skip
    nees, rms = _pose_nees(slam, run)
    assert 2.0 < nees < 15.0 and rms < 0.05  # measured 0.028 m
    assert all(feature.offset_size == 2 for feature in slam._state.features)
    white = _filter(run)
    white.config = dataclasses.replace(white.config, pixel_sigma_px=math.sqrt(5.0))
    assert _pose_nees(white, run)[0] > 15.0


def test_filter_waits_without_known_points_and_rejects_bad_frames() -> None:
    run = simulate_dynamic_scene(1, DynamicSceneConfig(duration_s=0.3, objects=0))
    slam = _filter(run)
    frame = run.frames[0]
    result = slam.process(MonoSlamFrame(frame.stamp_ns, frame.track_ids, frame.pixels))
    assert result.status == WAITING and result.centre is None
    assert any('waiting for the initialization target' in w for w in result.warnings)
    with pytest.raises(MonoSlamInputError, match='does not advance'):
        slam.process(MonoSlamFrame(frame.stamp_ns, frame.track_ids, frame.pixels))
    with pytest.raises(MonoSlamInputError, match='counts must match'):
        slam.process(MonoSlamFrame(frame.stamp_ns + 1, frame.track_ids[:2], frame.pixels))


def test_handovers_are_validated_and_enter_when_observed() -> None:
    run = simulate_dynamic_scene(4, DynamicSceneConfig(duration_s=1.0, objects=0))
    slam = _filter(run, initialize='handover')
    frames = list(_frames(run, InitTarget(), np.random.default_rng(1), static_only=True))
    first = slam.process(frames[0][1])
    assert first.status == TRACKING and first.added_ids == []  # nothing without handovers
    track_id = int(frames[1][0].track_ids[0])
    truth = run.point_positions[0, run.track_point[track_id]]
    assert 'not finite' in (slam.add_handover(track_id, np.array([np.nan, 0, 0]), np.eye(3))
                            or '')  # fmt: skip
    assert 'positive semi-definite' in (slam.add_handover(track_id, truth, -np.eye(3)) or '')
    assert slam.add_handover(track_id, truth, 0.01 * np.eye(3)) is None
    second = slam.process(frames[1][1])
    assert second.added_ids == [track_id]
    assert track_id in slam.owned_ids
    (point,) = [p for p in slam.map_points() if p.id == track_id]
    assert point.source == 'handover'
    assert np.linalg.norm(point.position - truth) < 0.5


def _handed_over_with_a_mover(
    probation: bool, shift_px: float, frames_run: int
) -> tuple[MonoSlam, int, list[tuple[int, dict[int, str], np.ndarray, bool]]]:
    """12 static points handed over at their true positions; one of them (returned) moves
    across the image at ``shift_px`` per frame (1 px: 0.3 m/s across the line of sight at
    ~9 m) after frame 10. Return the filter, the mover and per frame (index, removed, camera
    centre, whether the mover is on probation)."""
    run = simulate_dynamic_scene(4, DynamicSceneConfig(duration_s=frames_run / 30.0, objects=0))
    slam = _filter(run, initialize='handover', probation=probation)
    frames = list(_frames(run, InitTarget(), np.random.default_rng(1), static_only=True))
    slam.process(frames[0][1])
    seen = [int(i) for i in frames[0][0].track_ids if all(int(i) in f.track_ids for f, _ in
                                                           frames[:60])]  # fmt: skip
    handed = seen[:12]
    for track_id in handed:
        truth = run.point_positions[0, run.track_point[track_id]]
        assert slam.add_handover(track_id, truth, 1e-4 * np.eye(3)) is None
    mover = handed[0]
    steps = []
    for index, (_, measurements) in enumerate(frames[1:frames_run], start=1):
        pixels = measurements.pixels.copy()
        pixels[measurements.ids == mover, 0] += max(index - 10, 0) * shift_px
        result = slam.process(MonoSlamFrame(measurements.stamp_ns, measurements.ids, pixels,
                                            measurements.known_keys,
                                            measurements.known_pixels))  # fmt: skip
        assert result.status == TRACKING
        assert result.centre is not None
        on_probation = any(f.probation for f in slam._state.features if f.id == mover)
        steps.append((index, dict(result.removed), result.centre, on_probation))
    return slam, mover, steps


def test_a_handed_over_feature_that_moves_is_revoked_and_may_come_back() -> None:
    # without probation (every handover corrects the camera at once) SLAM revokes the mover
    # within 15 frames of its moving (removed 'revoked', no longer owned), and only it
    slam, mover, steps = _handed_over_with_a_mover(False, 1.0, 60)
    removed = {i: (index, why) for index, out, _, _ in steps for i, why in out.items()}
    assert removed.get(mover, (0, ''))[1] == 'revoked'
    assert removed[mover][0] - 10 <= 15
    assert mover not in slam.owned_ids
    assert not set(removed) - {mover}  # no static handover revoked
    position = np.array([9.0, 4.0, 1.0])  # handed over again (the Shadow filter's new fix)
    assert slam.add_handover(mover, position, 1e-4 * np.eye(3)) is None  # not refused


def test_a_mover_on_probation_cannot_move_the_camera_and_is_revoked_later() -> None:
    # with probation (the default) the handovers correct only themselves until SLAM's own
    # views fix them: while the mover is on probation the camera is exactly the camera of
    # the same run in which it stood still; once the static ones are trusted, it is revoked
    _, mover, steps = _handed_over_with_a_mover(True, 1.0, 150)
    _, _, still = _handed_over_with_a_mover(True, 0.0, 150)
    removed = {i: (index, why) for index, out, _, _ in steps for i, why in out.items()}
    assert removed.get(mover, (0, ''))[1] == 'revoked'
    assert not set(removed) - {mover}  # no static handover revoked
    both = [k for k, (a, b) in enumerate(zip(steps, still, strict=True)) if a[3] and b[3]]
    assert len(both) >= 30  # on probation in both runs for at least a second
    for k in both:
        np.testing.assert_array_equal(steps[k][2], still[k][2])


def test_losing_every_measurement_reports_lost_and_restarts() -> None:
    run = simulate_dynamic_scene(5, DynamicSceneConfig(duration_s=2.0, objects=0))
    slam = _filter(run)
    frames = list(_frames(run, InitTarget(), np.random.default_rng(2), static_only=True))
    statuses = [slam.process(m).status for _, m in frames[:10]]
    assert statuses == [TRACKING] * 10
    lost_at = None
    for index, (frame, _) in enumerate(frames[10:40], start=10):
        empty = MonoSlamFrame(frame.stamp_ns, np.zeros(0, np.int64), np.zeros((0, 2)))
        result = slam.process(empty)
        if result.status != TRACKING:
            lost_at = index
            assert any('tracking lost' in w for w in result.warnings)
            break
    assert lost_at is not None and lost_at - 10 <= slam.config.lost_after_frames
    assert slam.status == WAITING
    assert any(not p.active for p in slam.map_points())  # the map was retired, not dropped
    _, again = frames[lost_at + 1]
    assert slam.process(again).status == TRACKING


def test_known_points_the_estimate_disagrees_with_make_it_lost_and_restart() -> None:
    """A diverged estimate (here: the known corners seen half a turn away from where it
    expects them, features dropped) is lost once the known points in view disagree with it
    (rejected by the update, or reprojected beyond pixel noise after it) for
    lost_after_known_rejected_frames frames in a row, not after a single such frame."""
    run = simulate_dynamic_scene(5, DynamicSceneConfig(duration_s=2.0, objects=0))
    slam = _filter(run)
    frames = list(_frames(run, InitTarget(), np.random.default_rng(3), static_only=True))
    for _, measurements in frames[:10]:
        assert slam.process(measurements).status == TRACKING

    def shifted(index: int) -> MonoSlamFrame:
        measurements = frames[index][1]
        known = measurements.known_pixels[[2, 3, 0, 1]]  # the marker turned 180 degrees
        empty = np.zeros(0, np.int64), np.zeros((0, 2))
        return MonoSlamFrame(measurements.stamp_ns, *empty, measurements.known_keys, known)

    one = slam.process(shifted(10))
    assert one.status == TRACKING and one.known_points_used == 0  # rejected, not yet lost
    assert slam.process(frames[11][1]).status == TRACKING  # agreeing again: the count restarts
    limit = slam.config.lost_after_known_rejected_frames
    results = []
    for index in range(12, 12 + 3 * limit):
        results.append(slam.process(shifted(index)))
        if results[-1].status != TRACKING:
            break
    assert results[-1].status == LOST and len(results) == limit  # measured: gate alone, 5th
    assert any('known points in view disagree' in w for w in results[-1].warnings)
    restarted = slam.process(frames[12 + len(results)][1])
    assert restarted.status == TRACKING and restarted.known_points_used == 4


def test_a_collapsed_pose_covariance_makes_it_lost() -> None:
    """A pose covariance that is not positive definite (seen in a diverged run, eigenvalues
    from -3e-21 to 8e-4) must not be published and filtered on: lost, and it restarts."""
    run = simulate_dynamic_scene(5, DynamicSceneConfig(duration_s=1.0, objects=0))
    slam = _filter(run)
    frames = list(_frames(run, InitTarget(), np.random.default_rng(4), static_only=True))
    for _, measurements in frames[:5]:
        assert slam.process(measurements).status == TRACKING
    slam._state.p[0, 0] = -1.0  # a position variance below zero: no longer a covariance
    empty = MonoSlamFrame(frames[5][1].stamp_ns, np.zeros(0, np.int64), np.zeros((0, 2)))
    result = slam.process(empty)
    assert result.status == LOST
    assert any('pose covariance collapsed' in w for w in result.warnings)
    assert slam.process(frames[6][1]).status == TRACKING


def test_predictions_are_where_the_next_frame_sees_the_features() -> None:
    run = simulate_dynamic_scene(6, DynamicSceneConfig(duration_s=2.0, objects=0))
    slam = _filter(run)
    frames = list(_frames(run, InitTarget(), np.random.default_rng(3), static_only=True))
    for _, measurements in frames[:40]:
        slam.process(measurements)
    following, _ = frames[40]
    ids, pixels, regions, warps = slam.predictions(following.stamp_ns)
    assert len(ids) >= 10
    # each in-view feature's template warp to the next view: over the 1.3 s since the
    # templates were captured the camera moves little, so no feature looks much larger,
    # smaller or mirrored
    latest = set(frames[39][1].ids.tolist())
    near = [w for i, w, r in zip(ids, warps, regions, strict=True) if np.any(r) and i in latest]
    assert len(near) >= 10
    for warp in near:
        assert np.linalg.det(warp) > 0.0
        singular = np.linalg.svd(warp, compute_uv=False)
        assert np.all((singular > 0.7) & (singular < 1.4))
    seen = {int(i): p for i, p in zip(following.track_ids, following.true_pixels, strict=True)}
    distances = []
    margin = slam.config.view_margin_px
    for track_id, pixel, region in zip(ids, pixels, regions, strict=True):
        if not np.any(region):  # predicted out of view (MonoSlam._in_view): no search is due
            continue
        # a search only where the tracker can follow a feature: past the view margin
        assert margin <= pixel[0] <= slam.camera.width - 1 - margin
        assert margin <= pixel[1] <= slam.camera.height - 1 - margin
        assert np.all(np.linalg.eigvalsh(region) > 0.0)
        if int(track_id) in seen:
            error = seen[int(track_id)] - pixel
            distances.append(float(error @ np.linalg.solve(region, error)))
    assert len(distances) >= 10
    # true pixels fall inside the active search regions (chi-square 2 dof, 99.9 %: 13.8)
    assert np.median(distances) < 2.0 and max(distances) < 13.8
    _, _, only, _ = slam.predictions(following.stamp_ns, [int(ids[0])])
    assert len(only) == 1


def _loop_run(max_features: int = 100):  # type: ignore[no-untyped-def]
    scene = DynamicSceneConfig(duration_s=20.0, objects=0, loop_away_s=6.0, keep_track_ids=True)
    run = simulate_dynamic_scene(1, scene)
    slam = _filter(run)
    slam.config = dataclasses.replace(slam.config, max_features=max_features)
    steps = []
    for frame, measurements in _frames(run, InitTarget(), np.random.default_rng(3),
                                       static_only=True):  # fmt: skip
        result = slam.process(measurements)
        assert result.status == TRACKING
        assert result.centre is not None
        in_state = {feature.id for feature in slam._state.features}
        steps.append((result, in_state, np.linalg.norm(result.centre - frame.camera_position)))
    return scene, run, steps


def test_the_map_keeps_features_out_of_view_and_measures_them_when_they_return() -> None:
    # the loop scene with known data association (a point back in view has its old id): the
    # features mapped before the turn stay in the state while out of view, and most are
    # measured again within 5 frames of coming back (measured: 39 of 41); the error after the
    # return is well below the largest on the far side
    scene, run, steps = _loop_run()
    rate, loop = scene.rate_hz, scene.loop
    assert loop is not None
    start, back = int(loop.start_s * rate), int(loop.back_s * rate)
    mapped = steps[start][1]
    assert len(mapped) > 20
    returned = rematched = 0
    for feature_id in mapped:
        point = run.track_point[feature_id]
        seen = [k for k in range(back, len(steps)) if point in run.frames[k].point_ids]
        if not seen:
            continue
        returned += 1
        window = range(seen[0], min(seen[0] + 6, len(steps)))
        rematched += any(feature_id in steps[k][0].measured_ids for k in window)
    assert returned > 20 and rematched >= 0.8 * returned
    errors = np.array([error for _, _, error in steps])
    far_side = errors[int((loop.start_s + loop.turn_s) * rate) : back].max()
    assert np.sqrt(np.mean(errors[-30:] ** 2)) <= 0.5 * far_side


def test_a_full_state_evicts_the_least_measured_feature_out_of_view() -> None:
    """Each evicted feature was out of view, and measured in no more frames than any
    feature out of view that stayed (the landmarks a loop closes on stay)."""
    _, _, steps = _loop_run(max_features=30)
    evicted = [(k, i) for k, (result, _, _) in enumerate(steps)
               for i, why in result.removed.items() if why == 'evicted']  # fmt: skip
    assert evicted, 'nothing was evicted from a full state'
    measured_in: dict[int, int] = {}
    counts = []  # per frame: frames each feature was measured in, before it
    for result, _, _ in steps:
        counts.append(dict(measured_in))
        for i in result.measured_ids:
            measured_in[i] = measured_in.get(i, 0) + 1
    for k, feature_id in evicted:
        result, in_state, _ = steps[k]
        assert feature_id not in result.measured_ids
        assert len(in_state) <= 30
        busy = set(result.measured_ids) | set(result.rejected_ids) | set(result.searched_ids)
        busy |= set(result.added_ids)  # added after the eviction
        stayed = [counts[k].get(i, 0) for i in in_state - busy]
        assert not stayed or counts[k].get(feature_id, 0) <= min(stayed)


def test_a_feature_not_found_where_predicted_is_deleted() -> None:
    run = simulate_dynamic_scene(2, DynamicSceneConfig(duration_s=3.0, objects=0))
    slam = _filter(run)
    frames = list(_frames(run, InitTarget(), np.random.default_rng(0), static_only=True))
    removed: dict[int, tuple[int, str]] = {}
    hidden, found = None, 0
    for index, (_, measurements) in enumerate(frames):
        if index == 30:
            hidden = slam._state.features[0].id  # from now on the tracker never reports it
            found = slam._state.features[0].found
        keep = measurements.ids != hidden
        result = slam.process(dataclasses.replace(
            measurements, ids=measurements.ids[keep], pixels=measurements.pixels[keep]
        ))  # fmt: skip
        removed.update({i: (index, why) for i, why in result.removed.items()})
    assert hidden is not None and removed.get(hidden, (0, ''))[1] == 'failed'
    # Davison's rule: deleted once found in fewer than half of its searches (it was found in
    # every one of its first ``found``), and not before
    assert found - 1 <= removed[hidden][0] - 30 <= found + 1


def test_failures_in_a_row_are_of_consecutive_frames() -> None:
    """The persistent-outlier test deletes a feature rejected in max_consecutive_failures (3)
    frames in a row: a feature reported 40 px off in three frames in a row is deleted; one
    reported off in two frames, then not reported for a frame (out of view, dropped by the
    tracker), then off once more is not (its run ended with the frame it was not measured
    in; it was a loop's returning feature that carried two failures from before it left)."""
    run = simulate_dynamic_scene(2, DynamicSceneConfig(duration_s=2.0, objects=0))
    frames = list(_frames(run, InitTarget(), np.random.default_rng(0), static_only=True))
    for pattern, deleted in (('xxx', True), ('xx-x', False)):
        slam = _filter(run)
        target, removed = None, {}
        for index, (_, measurements) in enumerate(frames):
            ids, pixels = measurements.ids, measurements.pixels.copy()
            if index == 30:
                target = slam._state.features[0].id
            step = index - 30
            if target is not None and 0 <= step < len(pattern):
                if pattern[step] == '-':
                    keep = ids != target
                    ids, pixels = ids[keep], pixels[keep]
                else:
                    pixels[ids == target] += 40.0
            result = slam.process(dataclasses.replace(measurements, ids=ids, pixels=pixels))
            removed.update(result.removed)
            if step == len(pattern):
                break
        assert (target in removed) == deleted, (pattern, removed)
