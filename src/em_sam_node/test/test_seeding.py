"""The robust mode's first E-step (core.seeding): time steps, loop closure, outliers, movers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synthetic_room import MOVEABLE_IDS, STATIC_IDS, make_room
from test_continuation import corridor_loop

from em_sam_node.core.assembly import MappingData, build_problem, dead_reckoning, initial_estimate
from em_sam_node.core.em import _solve, run_em, seed_solver
from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.seeding import Seed, incremental_seed
from em_sam_node.core.structure import with_weak_priors
from slam_core.arrays import FloatArray

UNCALIBRATED = EmConfig(mode='robust', calibrate_odometry=False)


def seed_of(data: MappingData, config: EmConfig | None = None) -> Seed:
    config = config or EmConfig(mode='robust')
    return incremental_seed(data, config, seed_solver(config))


def rms_error(poses: FloatArray, truth: FloatArray) -> float:
    return float(np.sqrt(np.mean(np.sum((poses[:, :2] - truth[:, :2]) ** 2, axis=1))))


def least_squares(data: MappingData, start: FloatArray) -> FloatArray:
    """Plain SAM (every landmark static) from the given poses."""
    built = build_problem(data)
    problem = with_weak_priors(built.problem, np.zeros(0, dtype=np.int64), np.zeros((0, 3)))
    return _solve(EmConfig(), problem, initial_estimate(problem, start)).poses


def test_the_seed_finds_the_optimum_that_batch_least_squares_misses() -> None:
    """Odometry turning 0.04 rad too far every metre: from dead reckoning (17 m off), one
    Levenberg-Marquardt solve stops in another basin; the seed reaches the optimum that the
    same solve finds from the true poses (the odometry's own model: no calibration)."""
    data, truth = corridor_loop()
    optimum = least_squares(data, truth)
    assert rms_error(dead_reckoning(data), truth) > 10.0
    assert rms_error(least_squares(data, dead_reckoning(data)), optimum) > 1.0
    seed = seed_of(data, UNCALIBRATED)
    assert rms_error(seed.poses, optimum) < 0.05
    np.testing.assert_allclose(seed.poses[0], data.prior_pose, atol=1e-9)
    assert min(seed.weights.values()) > 0.5  # the posts did not move: none is distrusted


def test_a_misread_sighting_does_not_bend_the_seed() -> None:
    """A barcode read as another one far away: a single sighting that fits nothing."""
    data, truth = corridor_loop()
    optimum = least_squares(data, truth)
    clean = rms_error(seed_of(data, UNCALIBRATED).poses, optimum)
    wrong = np.flatnonzero(data.obs_keyframe == 45)[:2]
    ids = data.obs_landmark_id.copy()
    ids[wrong] = (ids[wrong] + 10) % (ids.max() + 1)
    misread = seed_of(dataclasses.replace(data, obs_landmark_id=ids), UNCALIBRATED)
    assert rms_error(misread.poses, optimum) < clean + 0.02


def test_a_moved_landmark_stops_pulling_before_the_main_loop() -> None:
    """A step that sees it elsewhere cuts its later sightings off as a new landmark, or (seen
    on both sides of the move within one step) its weight drops in that step's EM rounds."""
    room = make_room(0)
    seed = seed_of(room.data)
    assert all(seed.clusters.get(i, 1) > 1 or seed.weights[i] < 0.5 for i in MOVEABLE_IDS)
    assert not set(seed.clusters) & set(STATIC_IDS)
    assert all(seed.weights[i] > 0.5 for i in STATIC_IDS)
    assert rms_error(seed.poses, room.true_poses) < 0.1


@pytest.mark.parametrize('chunk_s', [7.0, 20.0, 33.0])
def test_the_robust_mode_does_not_depend_on_the_step_length(chunk_s: float) -> None:
    data, truth = corridor_loop(1)
    optimum = least_squares(data, truth)
    config = dataclasses.replace(UNCALIBRATED, seed_chunk_s=chunk_s)
    result = run_em(data, config, record_snapshots=False)
    assert not result.moveable.any()
    assert rms_error(result.poses, optimum) < 0.05
    # Calibrated (the default), the heading bias is estimated as a drift per metre: as
    # close to the truth as the uncalibrated optimum, or closer.
    calibrated = run_em(
        data, EmConfig(mode='robust', seed_chunk_s=chunk_s), record_snapshots=False
    )
    assert not calibrated.moveable.any()
    assert rms_error(calibrated.poses, truth) <= rms_error(optimum, truth) + 0.01
