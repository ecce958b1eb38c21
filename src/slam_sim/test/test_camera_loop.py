"""The loop scene's camera (``camera_path.LoopTurn``): it turns away from the start area for
``loop_away_s`` and comes back to the very view it left; outside the turn the run is the
plain scene of the same seed; a loop that cannot end within the run is refused."""

from __future__ import annotations

import dataclasses
import importlib
import math

import numpy as np
import pytest

from slam_sim.core.camera_path import LoopTurn
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_room import FAR_WALL_FRACTION
from slam_sim.core.dynamic_scene import simulate_dynamic_scene


def test_the_yaw_ramps_out_holds_and_ramps_back() -> None:
    turn = LoopTurn(start_s=2.0, turn_s=1.0, away_s=5.0, angle_rad=math.pi / 2)
    times = np.array([0.0, 2.0, 2.5, 3.0, 5.0, 8.0, 8.5, 9.0, 12.0])
    yaw = turn.yaw_at(times)
    np.testing.assert_allclose(yaw[[0, 1, 7, 8]], 0.0, atol=1e-12)
    np.testing.assert_allclose(yaw[[3, 4, 5]], math.pi / 2)
    np.testing.assert_allclose(yaw[[2, 6]], math.pi / 4)
    assert turn.back_s == 9.0


LOOP_WALL = round(FAR_WALL_FRACTION * DynamicSceneConfig().static_points)


def test_a_loop_run_leaves_the_start_view_and_returns_to_it() -> None:
    plain = DynamicSceneConfig(duration_s=14.0, objects=2)
    loop = dataclasses.replace(plain, loop_away_s=6.0, loop_start_s=2.0, loop_turn_s=1.0)
    assert loop.loop is not None and plain.loop is None
    run, reference = simulate_dynamic_scene(5, loop), simulate_dynamic_scene(5, plain)
    rate = plain.rate_hz
    before, away, after = int(1.5 * rate), int(6.0 * rate), int(loop.loop.back_s * rate) + 1
    for k in (before, after, len(run.frames) - 1):  # outside the turn: the plain run
        np.testing.assert_allclose(
            run.frames[k].camera_rotation, reference.frames[k].camera_rotation
        )
        # the same points (re-entering ones under new track ids), and perhaps some of the wall
        # the loop turns to (its points come after the room's, before the objects')
        ids = run.frames[k].point_ids
        wall = (ids >= plain.static_points) & (ids < plain.static_points + LOOP_WALL)
        shifted = np.where(ids >= plain.static_points + LOOP_WALL, ids - LOOP_WALL, ids)
        np.testing.assert_array_equal(
            np.sort(shifted[~wall]), np.sort(reference.frames[k].point_ids)
        )
    forward = run.frames[away].camera_rotation[:, 2]
    start = run.frames[before].camera_rotation[:, 2]
    assert math.degrees(math.acos(np.clip(forward @ start, -1, 1))) > 60.0  # turned away
    seen_before = set(run.frames[before].point_ids.tolist())
    assert len(seen_before & set(run.frames[away].point_ids.tolist())) < 0.2 * len(seen_before)
    np.testing.assert_allclose(
        run.frames[away].camera_position, reference.frames[away].camera_position
    )  # the centre keeps its path: only the view turns


def test_a_loop_that_does_not_end_within_the_run_is_refused() -> None:
    with pytest.raises(ValueError, match='loop_away_s'):
        DynamicSceneConfig(duration_s=8.0, loop_away_s=6.0, loop_start_s=2.0, loop_turn_s=1.0)
    with pytest.raises(ValueError, match='loop_turn_s'):
        DynamicSceneConfig(loop_turn_s=0.0)


@pytest.mark.parametrize('module', ['dynamic_features_bag', 'dynamic_camera_bag'])
def test_both_simulators_take_the_loop_and_name_a_bad_one(
    module: str, capsys: pytest.CaptureFixture[str]
) -> None:
    cli = importlib.import_module(f'slam_sim.{module}')
    parser = cli._parser()
    good = parser.parse_args(['--seed', '1', '--output', 'x.mcap', '--loop-away-s', '6'])
    assert cli._config(parser, good).loop_away_s == 6.0
    bad = parser.parse_args(
        ['--seed', '1', '--output', 'x.mcap', '--duration-s', '8', '--loop-away-s', '6']
    )
    with pytest.raises(SystemExit):
        cli._config(parser, bad)
    assert '--loop-away-s' in capsys.readouterr().err


def test_known_data_association_gives_a_returning_point_its_id_back() -> None:
    plain = DynamicSceneConfig(
        duration_s=14.0, objects=0, loop_away_s=6.0, loop_start_s=2.0, loop_turn_s=1.0
    )
    for keep in (False, True):
        run = simulate_dynamic_scene(5, dataclasses.replace(plain, keep_track_ids=keep))
        ids_of: dict[int, set[int]] = {}
        for frame in run.frames:
            for point, track in zip(
                frame.point_ids.tolist(), frame.track_ids.tolist(), strict=True
            ):
                ids_of.setdefault(point, set()).add(track)
        returned = [point for point in run.frames[0].point_ids.tolist()
                    if point in run.frames[-1].point_ids.tolist()]  # fmt: skip
        assert len(returned) > 50
        if keep:
            assert all(len(ids_of[point]) == 1 for point in returned)
        else:
            assert all(len(ids_of[point]) > 1 for point in returned)


def test_the_wall_the_loop_turns_to_has_as_many_points_as_the_far_wall() -> None:
    plain = DynamicSceneConfig(duration_s=14.0, objects=0)
    loop = dataclasses.replace(plain, loop_away_s=6.0, loop_start_s=2.0, loop_turn_s=1.0)
    run = simulate_dynamic_scene(5, loop)
    static = run.scene.static_points_m
    assert len(static) == plain.static_points + LOOP_WALL
    wall = static[plain.static_points :]
    np.testing.assert_allclose(wall[:, 1], 8.0)  # turned +90 deg from +x: the y = 8 m wall
    assert np.all((wall[:, 0] >= 0.0) & (wall[:, 0] <= 5.0) & (wall[:, 2] <= 3.0))
    away = run.frames[int(6.0 * loop.rate_hz)]
    assert np.count_nonzero(away.point_ids >= plain.static_points) >= 0.5 * LOOP_WALL
