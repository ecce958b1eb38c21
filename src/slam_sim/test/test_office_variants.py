"""simulate_office: determinism, the move, and each variant's defining property."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import pytest

from slam_sim.core.office import OfficeRun, Variant, simulate_office
from slam_sim.core.world import OFFICE_1, OFFICE_2

RunFactory = Callable[[int, str], OfficeRun]


def _arrays(value: object) -> list[np.ndarray]:
    """Every numpy array inside nested dataclasses, in field order."""
    if isinstance(value, np.ndarray):
        return [value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return [a for f in dataclasses.fields(value) for a in _arrays(getattr(value, f.name))]
    return []


def test_same_seed_same_run_other_seed_other_run(office_run: RunFactory) -> None:
    first, again = simulate_office(11, 'standard'), simulate_office(11, 'standard')
    for a, b in zip(_arrays(first), _arrays(again), strict=True):
        np.testing.assert_array_equal(a, b)
    other = office_run(7, 'standard').observations
    assert len(other) != len(first.observations) or not np.array_equal(
        other.range_m, first.observations.range_m
    )


def test_unknown_variant_names_the_choices() -> None:
    with pytest.raises(ValueError, match='one_position'):
        simulate_office(1, 'moving')


def test_moveable_markers_move_while_the_robot_is_in_the_corridor(
    office_run: RunFactory,
) -> None:
    run = office_run(7, 'standard')
    truth = run.landmarks
    assert truth.move_time_ns is not None
    pose = run.truth.poses_at(np.array([truth.move_time_ns]))[0]
    assert run.world.room_of(pose[None, :2]) == ('corridor',)
    moved = truth.moved
    assert moved.tolist() == truth.moveable.tolist()
    assert {truth.rooms_before[i] for i in np.nonzero(moved)[0]} == {OFFICE_1}
    assert {truth.rooms_after[i] for i in np.nonzero(moved)[0]} == {OFFICE_2}


def test_standard_seed_7_sees_every_moveable_marker_at_both_positions(
    office_run: RunFactory,
) -> None:
    run = office_run(7, 'standard')
    assert run.seen_at_both_positions.tolist() == list(range(100, 110))


def test_static_variant_moves_nothing(office_run: RunFactory) -> None:
    run = office_run(7, 'static')
    assert run.landmarks.move_time_ns is None
    assert not run.landmarks.moved.any()
    assert run.seen_at_both_positions.size == 0


def test_all_moveable_is_the_standard_run_without_static_observations(
    office_run: RunFactory,
) -> None:
    standard, only_moveable = office_run(7, 'standard'), office_run(7, 'all_moveable')
    obs = only_moveable.observations
    assert np.all(obs.landmark_ids >= 100)
    keep = standard.observations.landmark_ids >= 100
    np.testing.assert_array_equal(obs.range_m, standard.observations.range_m[keep])
    np.testing.assert_array_equal(obs.stamps_ns, standard.observations.stamps_ns[keep])


def test_coherent_variant_moves_the_desks_by_one_rigid_transform(
    office_run: RunFactory,
) -> None:
    truth = office_run(7, 'coherent').landmarks
    before = truth.positions_before_m[truth.moveable]
    after = truth.positions_after_m[truth.moveable]
    # Kabsch: the best rotation and translation mapping before onto after.
    mean_b, mean_a = before.mean(axis=0), after.mean(axis=0)
    u, _, vt = np.linalg.svd((before - mean_b).T @ (after - mean_a))
    rotation = (u @ vt).T
    residual = after - ((before - mean_b) @ rotation.T + mean_a)
    assert np.abs(residual).max() < 1e-9
    normals_turned = truth.normals_before[truth.moveable] @ rotation.T
    np.testing.assert_allclose(normals_turned, truth.normals_after[truth.moveable], atol=1e-9)
    shift = np.linalg.norm(after - before, axis=1)
    assert shift.min() > 0.7 and shift.max() < 1.2
    assert {truth.rooms_after[i] for i in np.nonzero(truth.moveable)[0]} == {OFFICE_1}


def test_one_position_variant_hides_some_moved_markers(office_run: RunFactory) -> None:
    run = office_run(7, 'one_position')
    truth, obs = run.landmarks, run.observations
    moved_ids = set(truth.ids[truth.moved].tolist())
    unseen_twice = moved_ids - set(run.seen_at_both_positions.tolist())
    assert len(unseen_twice) == run.config.one_position_count == 4
    after = truth.after_move(obs.stamps_ns)
    for landmark_id in unseen_twice:
        mine = obs.landmark_ids == landmark_id
        assert mine[~after].any() and not mine[after].any()


def test_variants_share_the_robot_run(office_run: RunFactory) -> None:
    standard = office_run(7, 'standard')
    static_obs = standard.observations.landmark_ids < 100
    for variant in (Variant.STATIC, Variant.COHERENT, Variant.ONE_POSITION):
        run = office_run(7, variant.value)
        np.testing.assert_array_equal(run.odometry.poses, standard.odometry.poses)
        mine = run.observations.landmark_ids < 100
        np.testing.assert_array_equal(
            run.observations.range_m[mine], standard.observations.range_m[static_obs]
        )


def test_run_is_a_few_minutes_with_many_observations(office_run: RunFactory) -> None:
    run = office_run(7, 'standard')
    assert 150.0 < run.duration_s < 600.0
    ids, counts = np.unique(run.observations.landmark_ids, return_counts=True)
    assert ids.tolist() == run.landmarks.ids.tolist()  # every marker is seen
    assert counts.min() >= 5
