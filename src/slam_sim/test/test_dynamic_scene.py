"""The dynamic-scene simulation (core.dynamic_scene) and its feature bag, on short runs."""

from __future__ import annotations

import dataclasses
from functools import cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from slam_ros.bag.source import BagSource
from slam_ros.typesys import TypeRegistry
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import DynamicSceneRun, build_scene, simulate_dynamic_scene
from slam_sim.dynamic_features_bag import (
    CAMERA_INFO_TOPIC,
    CAMERA_POSE_TOPIC,
    FEATURES_TOPIC,
    TOPICS,
    TRUE_FEATURES_TOPIC,
    main,
    write_dynamic_features_bag,
)

SHORT = DynamicSceneConfig(duration_s=3.0)


@cache
def _run(seed: int, config: DynamicSceneConfig = SHORT) -> DynamicSceneRun:
    return simulate_dynamic_scene(seed, config)


def _object_points(run: DynamicSceneRun, kind: str) -> list[int]:
    """The first point of every object of ``kind``."""
    objects = [i for i, k in enumerate(run.object_motion) if k == kind]
    return [int(np.flatnonzero(run.point_object == i)[0]) for i in objects]


def test_same_seed_gives_the_same_run_and_other_seeds_differ() -> None:
    first, again = simulate_dynamic_scene(5, SHORT), simulate_dynamic_scene(5, SHORT)
    other = simulate_dynamic_scene(6, SHORT)
    np.testing.assert_array_equal(first.point_positions, again.point_positions)
    assert first.track_point == again.track_point
    for a, b in zip(first.frames, again.frames, strict=True):
        assert a.stamp_ns == b.stamp_ns
        np.testing.assert_array_equal(a.track_ids, b.track_ids)
        np.testing.assert_array_equal(a.pixels, b.pixels)
        np.testing.assert_array_equal(a.camera_rotation, b.camera_rotation)
    assert not np.allclose(first.point_positions, other.point_positions)
    assert not np.allclose(first.frames[0].camera_position, other.frames[0].camera_position)


def test_noise_free_pixels_are_opencv_projections_inside_the_image() -> None:
    run = _run(3, DynamicSceneConfig(duration_s=2.0, pixel_noise_px=0.0))
    camera = run.camera
    margin = run.config.image_margin_px
    for k, frame in enumerate(run.frames[::10]):
        rotation, position = frame.camera_rotation, frame.camera_position
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        np.testing.assert_array_equal(frame.pixels, frame.true_pixels)
        world = run.point_positions[10 * k, frame.point_ids]
        rvec, _ = cv2.Rodrigues(rotation.T)
        expected, _ = cv2.projectPoints(
            world, rvec, -rotation.T @ position, camera.K, camera.camera_info().d
        )
        np.testing.assert_allclose(frame.true_pixels, expected.reshape(-1, 2), atol=1e-6)
        assert np.all(frame.true_pixels >= margin)
        assert np.all(frame.true_pixels <= [camera.width - 1 - margin, camera.height - 1 - margin])


def test_pixel_noise_has_the_configured_spread() -> None:
    run = _run(4, DynamicSceneConfig(duration_s=2.0, pixel_noise_px=1.5))
    errors = np.vstack([f.pixels - f.true_pixels for f in run.frames])
    assert len(errors) > 5000
    np.testing.assert_allclose(errors.std(axis=0), 1.5, rtol=0.05)
    np.testing.assert_allclose(errors.mean(axis=0), 0.0, atol=0.05)


def test_tracking_offsets_vary_slowly_jump_and_leave_other_runs_alone() -> None:
    # 2 px offsets correlated over 1 s (a = exp(-1/30) from frame to frame), jumps 2 %/frame;
    # white noise 0 to see them alone. The run without offsets is unchanged.
    config = DynamicSceneConfig(duration_s=4.0, pixel_noise_px=0.0, tracking_offset_px=2.0,
                                tracking_jump_probability=0.02)  # fmt: skip
    run = _run(4, config)
    errors = np.vstack([f.pixels - f.true_pixels for f in run.frames])
    np.testing.assert_allclose(errors.std(axis=0), 2.0, rtol=0.1)
    pairs, steps = [], []
    for previous, frame in zip(run.frames, run.frames[1:], strict=False):
        _, mine, theirs = np.intersect1d(frame.track_ids, previous.track_ids, return_indices=True)
        before = previous.pixels[theirs] - previous.true_pixels[theirs]
        after = frame.pixels[mine] - frame.true_pixels[mine]
        pairs.append(np.column_stack([before[:, 0], after[:, 0]]))
        steps.append(np.linalg.norm(after - before, axis=1))
    lag = np.vstack(pairs)
    correlation = np.corrcoef(lag[:, 0], lag[:, 1])[0, 1]
    # a step of the slow process is N(0, 0.51^2) per axis (2 sqrt(1 - a^2)): above 2.5 px with
    # probability 6e-6; a jump (a fresh N(0, 2^2) draw) is, 68 % of the time: 1.4 % of steps
    jumps = np.concatenate(steps) > 2.5
    assert correlation > 0.9  # measured 0.95: a = exp(-1/30), less the jumps
    assert 0.008 < jumps.mean() < 0.02
    plain = dataclasses.replace(config, tracking_offset_px=0.0, tracking_jump_probability=0.0)
    without = _run(4, plain)
    assert all(np.array_equal(f.pixels, f.true_pixels) for f in without.frames)
    with pytest.raises(ValueError, match='tracking_offset_px'):
        DynamicSceneConfig(tracking_offset_px=-1.0)


def test_track_ids_are_never_reused_and_name_one_point() -> None:
    run = _run(2, DynamicSceneConfig(duration_s=3.0, track_drop_probability=0.05))
    seen_frames: dict[int, list[int]] = {}
    newest = 0
    previous: dict[int, int] = {}  # point -> track id in the previous frame
    for k, frame in enumerate(run.frames):
        ids = frame.track_ids.tolist()
        assert ids == sorted(set(ids)) and min(ids) >= 1
        for track_id, point in zip(ids, frame.point_ids.tolist(), strict=True):
            assert run.track_point[track_id] == point
            if track_id > newest:  # a new track: its point was not tracked just before
                assert previous.get(point) is None
            seen_frames.setdefault(track_id, []).append(k)
        new_ids = [i for i in ids if i > newest]
        assert new_ids == list(range(newest + 1, newest + 1 + len(new_ids)))
        newest = max(newest, *ids)
        previous = dict(zip(frame.point_ids.tolist(), ids, strict=True))
    assert set(seen_frames) == set(run.track_point) == set(range(1, newest + 1))
    for frames in seen_frames.values():  # each id lives in consecutive frames only
        assert frames == list(range(frames[0], frames[-1] + 1))
    assert len(seen_frames) > len(set(run.track_point.values()))  # drops made new ids


def test_enough_static_points_are_visible_in_every_frame() -> None:
    for seed in range(3):
        for focal_px in (300.0, 500.0):
            run = _run(seed, DynamicSceneConfig(duration_s=20.0, focal_px=focal_px))
            static = [np.count_nonzero(~run.point_moving[f.point_ids]) for f in run.frames]
            moving = [np.count_nonzero(run.point_moving[f.point_ids]) for f in run.frames]
            assert min(static) >= 40, (seed, focal_px)
            assert np.mean(moving) >= 12, (seed, focal_px)


def test_constant_velocity_objects_keep_their_velocity_between_bounces() -> None:
    run = _run(1, DynamicSceneConfig(duration_s=20.0))
    dt_s = 1.0 / run.config.rate_hz
    for point in _object_points(run, 'constant_velocity'):
        velocity = run.point_velocities[:, point]
        start = velocity[0]
        assert 0.3 <= np.linalg.norm(start) <= 1.0 and start[2] == 0.0
        np.testing.assert_allclose(np.abs(velocity), np.abs(start)[None].repeat(len(velocity), 0))
        steady = np.all(velocity[1:] == velocity[:-1], axis=1)
        assert steady.mean() > 0.95
        steps = np.diff(run.point_positions[:, point], axis=0)
        np.testing.assert_allclose(steps[steady], velocity[1:][steady] * dt_s, atol=1e-12)


def test_turning_objects_keep_their_speed_and_turn_steadily() -> None:
    run = _run(1, DynamicSceneConfig(duration_s=5.0, motions=('turning',), objects=3))
    for point in _object_points(run, 'turning'):
        velocity = run.point_velocities[:, point]
        speed = np.linalg.norm(velocity, axis=1)
        np.testing.assert_allclose(speed, speed[0], rtol=1e-12)
        heading_rate = np.diff(np.unwrap(np.arctan2(velocity[:, 1], velocity[:, 0])))
        np.testing.assert_allclose(heading_rate, heading_rate[0], atol=1e-9)
        assert 0.3 <= abs(heading_rate[0]) * run.config.rate_hz <= 1.0
        steps = np.diff(run.point_positions[:, point], axis=0) * run.config.rate_hz
        mean_velocity = 0.5 * (velocity[1:] + velocity[:-1])
        np.testing.assert_allclose(steps, mean_velocity, atol=1e-3)


def test_stop_and_go_objects_stop_completely_between_moving_stretches() -> None:
    run = _run(2, DynamicSceneConfig(duration_s=10.0, motions=('stop_and_go',), objects=2))
    rate = run.config.rate_hz
    for point in _object_points(run, 'stop_and_go'):
        velocity = run.point_velocities[:, point]
        stopped = np.all(velocity == 0.0, axis=1)
        assert 0.05 < stopped.mean() < 0.5
        assert np.all(np.linalg.norm(velocity[~stopped], axis=1) >= 0.3 - 1e-12)
        positions = run.point_positions[:, point]
        still = stopped[1:] & stopped[:-1]
        np.testing.assert_array_equal(positions[1:][still], positions[:-1][still])
        edges = np.flatnonzero(np.diff(stopped.astype(int)))
        lengths = np.diff(edges) / rate  # alternating stops and stretches between edges
        assert np.all(lengths >= 0.3 - 2.0 / rate) and np.all(lengths <= 3.0 + 2.0 / rate)


def test_model_objects_follow_the_shadow_filter_process_model() -> None:
    config = DynamicSceneConfig(duration_s=10.0, motions=('model',), objects=20)
    run = _run(8, config)
    dt_s = 1.0 / config.rate_hz
    points = _object_points(run, 'model')
    assert len(points) == 20 and np.count_nonzero(run.point_moving) == 20  # one point each
    increments, later = [], []
    for point in points:  # the walk after each object's birth frame
        birth = run.point_birth_frame[point]
        velocity = run.point_velocities[birth:, point]
        increments.append(np.diff(velocity, axis=0))
        steps = np.diff(run.point_positions[birth:, point], axis=0)
        np.testing.assert_allclose(steps, velocity[1:] * dt_s, atol=1e-12)
        later.append(increments[-1][1:])
    every = np.concatenate(increments)
    np.testing.assert_allclose(every.var(), config.acceleration_psd * dt_s, rtol=0.05)
    lagged = np.concatenate([i[:-1] for i in increments])
    assert abs(np.corrcoef(np.concatenate(later).ravel(), lagged.ravel())[0, 1]) < 0.05


def test_scene_geometry_is_continuous_in_time() -> None:
    run = _run(0)
    scene = run.scene
    times = np.arange(len(run.frames)) / run.config.rate_hz
    positions, _ = scene.point_states_at(times)
    np.testing.assert_array_equal(positions, run.point_positions)
    path, h = scene.camera_path, 1e-6
    samples = np.linspace(0.1, 2.9, 13)
    numeric = (path.positions_at(samples + h) - path.positions_at(samples - h)) / (2 * h)
    np.testing.assert_allclose(path.velocities_at(samples), numeric, atol=1e-6)
    times = np.linspace(0.0, 20.0, 400)
    speed = np.linalg.norm(path.velocities_at(times), axis=1)
    assert speed.max() < 1.6  # walking loop plus the hand's sweep
    steady = build_scene(dataclasses.replace(run.config, hand_motion_m=0.0), 0).camera_path
    walk = np.linalg.norm(steady.velocities_at(times), axis=1)
    assert walk.min() > 0.15 and walk.max() < 1.0  # the loop alone: walking pace
    hand = path.velocities_at(times) - steady.velocities_at(times)
    assert 0.1 < np.linalg.norm(hand, axis=1).max() < 1.0  # ±0.1 m at 0.4-0.9 Hz per axis


def test_focal_length_outside_150_to_500_px_is_rejected_by_name() -> None:
    for focal_px in (149.0, 501.0):
        with pytest.raises(ValueError, match='focal_px'):
            DynamicSceneConfig(focal_px=focal_px)
    for focal_px in (150.0, 500.0):
        assert DynamicSceneConfig(focal_px=focal_px).camera().fx == focal_px
    with pytest.raises(ValueError, match='motions'):
        DynamicSceneConfig(motions=('teleport',))


def test_the_camera_is_plumb_bob_with_the_configured_focal_length() -> None:
    info = DynamicSceneConfig(focal_px=310.0).camera().camera_info()
    assert (info.width, info.height, info.distortion_model) == (640, 480, 'plumb_bob')
    np.testing.assert_array_equal(info.k, [310, 0, 320.7, 0, 310, 238.9, 0, 0, 1])
    np.testing.assert_array_equal(info.d, [-0.05, 0, 0, 0, 0])
    np.testing.assert_array_equal(info.p, [310, 0, 320.7, 0, 0, 310, 238.9, 0, 0, 0, 1, 0])


def _read(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """Every message of the bag by topic: (bag stamp ns, deserialized message)."""
    registry = TypeRegistry()
    messages: dict[str, list[tuple[int, Any]]] = {}
    with BagSource(path) as source:
        for message in source.messages():
            registry.ensure(message.msgtype)
            decoded = registry.typestore.deserialize_cdr(message.data, message.msgtype)
            messages.setdefault(message.topic, []).append((message.timestamp_ns, decoded))
    return messages


def _stamp_ns(message: Any) -> int:
    return int(message.header.stamp.sec) * 10**9 + int(message.header.stamp.nanosec)


def test_bag_round_trip_keeps_stamps_features_and_truth(tmp_path: Path) -> None:
    run = _run(0, DynamicSceneConfig(duration_s=1.0))
    written = write_dynamic_features_bag(run, tmp_path / 'features.mcap')
    with BagSource(written.path) as source:
        topics = {name: (t.msgtype, t.count) for name, t in source.topics().items()}
    assert topics == {topic: (msgtype, len(run.frames)) for topic, msgtype in TOPICS}
    messages = _read(written.path)
    stamps = [frame.stamp_ns for frame in run.frames]
    for topic, _ in TOPICS:
        assert [stamp for stamp, _ in messages[topic]] == stamps
        assert [_stamp_ns(message) for _, message in messages[topic]] == stamps
    _, info = messages[CAMERA_INFO_TOPIC][0]
    np.testing.assert_array_equal(info.k, run.camera.camera_info().k)
    for frame, (_, features), (_, truth), (_, pose) in zip(
        run.frames,
        messages[FEATURES_TOPIC],
        messages[TRUE_FEATURES_TOPIC],
        messages[CAMERA_POSE_TOPIC],
        strict=True,
    ):
        assert features.header.frame_id == 'camera_optical_frame'
        assert [t.id for t in features.tracks] == frame.track_ids.tolist()
        np.testing.assert_array_equal([(t.u, t.v) for t in features.tracks], frame.pixels)
        assert truth.header.frame_id == 'map' and pose.header.frame_id == 'map'
        expected = [2 if run.point_moving[run.track_point[t.id]] else 1 for t in truth.tracks]
        assert [t.status for t in truth.tracks] == expected
        assert all(np.isnan(t.test_statistic) and t.test_dof == 0 for t in truth.tracks)
        p = pose.pose.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], frame.camera_position)
        q = pose.pose.pose.orientation
        z_axis = [
            2 * (q.x * q.z + q.y * q.w),
            2 * (q.y * q.z - q.x * q.w),
            1 - 2 * (q.x**2 + q.y**2),
        ]
        np.testing.assert_allclose(z_axis, frame.camera_rotation[:, 2], atol=1e-12)
    statuses = {t.status for _, m in messages[TRUE_FEATURES_TOPIC] for t in m.tracks}
    assert statuses == {1, 2}


def test_command_line_writes_refuses_to_overwrite_and_replaces_with_force(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    output = tmp_path / 'run.mcap'
    argv = ['--seed', '3', '--output', str(output), '--duration-s', '0.5', '--motions', 'model']
    assert main(argv) == 0
    assert '15 frames' in capsys.readouterr().out
    assert main(argv) == 2
    assert 'pass --force' in capsys.readouterr().err
    assert main([*argv, '--force']) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ['run.mcap']
    with pytest.raises(SystemExit):
        main([*argv, '--force', '--focal-px', '600'])
    assert '--focal-px' in capsys.readouterr().err


def test_model_objects_are_born_with_the_filter_prior_and_unseen_before() -> None:
    config = DynamicSceneConfig(duration_s=10.0, motions=('model',), objects=40)
    run = _run(5, config)
    points = _object_points(run, 'model')
    births = run.point_birth_frame[points]
    assert births.min() >= 0 and births.max() < config.frame_count // 2
    assert len(np.unique(births)) > 20  # spread over the first half, not all at frame 0
    for index, frame in enumerate(run.frames):
        assert np.all(run.point_birth_frame[frame.point_ids] <= index)  # unseen before birth
    at_birth = run.point_velocities[births, points]
    assert 0.35 < at_birth.std() < 0.65  # v_b ~ N(0, 0.5^2) per axis, 120 samples
    assert np.all(run.point_birth_frame[~run.point_moving] == 0)
