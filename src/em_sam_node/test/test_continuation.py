"""core.continuation: least squares by continuation in time, from dead reckoning."""

from __future__ import annotations

import dataclasses

import numpy as np
from synthetic_room import SECOND_NS, chained_data

from em_sam_node.core.assembly import MappingData, build_problem, dead_reckoning, initial_estimate
from em_sam_node.core.continuation import incremental_least_squares, step_ends
from em_sam_node.core.factors import range_bearing_predict
from em_sam_node.core.problem import Estimate, SlamProblem
from em_sam_node.core.solver import solve
from em_sam_node.core.structure import with_weak_priors
from slam_core.arrays import FloatArray
from slam_core.geometry.se2 import increment_between

OBSERVATION_SIGMA = np.array([0.05, 0.01])  # m, rad
ODOMETRY_SIGMA = np.array([0.02, 0.02, 0.045])  # per 1 m step: m, m, rad (covers the bias)
HEADING_BIAS_RAD = 0.04  # per step: an uncalibrated wheel base, 6 rad over the two loops


def least_squares(problem: SlamProblem, start: Estimate) -> Estimate:
    return solve(problem, start, method='levenberg_marquardt').estimate


def rms_error(poses: FloatArray, truth: FloatArray) -> float:
    return float(np.sqrt(np.mean(np.sum((poses[:, :2] - truth[:, :2]) ** 2, axis=1))))


def corridor_loop(seed: int = 0) -> tuple[MappingData, FloatArray]:
    """A 30 m x 8 m rectangular loop driven twice in 1 m steps, posts every 3 m along both
    sides of the track; the odometry turns HEADING_BIAS_RAD too far every step."""
    corners = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 8.0], [0.0, 8.0]])
    points = []
    for a, b in zip(corners, np.roll(corners, -1, axis=0), strict=True):
        length = int(np.linalg.norm(b - a))
        points += [a + (b - a) * s / length for s in range(length)]
    track = np.array(points * 2 + [points[0]])
    heading = np.arctan2(*(np.roll(track, -1, axis=0) - track)[:, ::-1].T)
    heading[-1] = heading[-2]
    poses = np.column_stack([track, heading])
    rng = np.random.default_rng(seed)
    u = increment_between(poses[:-1], poses[1:])
    u = u + rng.normal(0.0, 1.0, u.shape) * ODOMETRY_SIGMA
    u[:, 2] += HEADING_BIAS_RAD
    posts = np.array(
        [(x, y) for x in np.arange(1.5, 30.0, 3.0) for y in (-1.5, 9.5)]
        + [(x, y) for x in (-1.5, 31.5) for y in np.arange(1.0, 8.0, 3.0)]
    )
    keyframes, ids, z = [], [], []
    for index, pose in enumerate(poses):
        predicted = range_bearing_predict(np.repeat(pose[None], len(posts), 0), posts)
        for j in np.flatnonzero((predicted[:, 0] < 6.0) & (np.abs(predicted[:, 1]) < 1.4)):
            keyframes.append(index)
            ids.append(int(j))
            z.append(predicted[j] + rng.normal(0.0, 1.0, 2) * OBSERVATION_SIGMA)
    data = chained_data(poses[0], u, ODOMETRY_SIGMA, (keyframes, ids, z), OBSERVATION_SIGMA)
    return data, poses


def batch(data: MappingData, start: FloatArray) -> FloatArray:
    """One least-squares solve (every landmark static) from the given poses."""
    built = build_problem(data)
    problem = with_weak_priors(built.problem, np.zeros(0, dtype=np.int64), np.zeros((0, 3)))
    return least_squares(problem, initial_estimate(problem, start)).poses


def test_steps_grow_with_the_time_solved_and_end_at_the_last_keyframe() -> None:
    stamps = np.arange(2001, dtype=np.int64) * SECOND_NS  # 2000 s, one keyframe a second
    ends = step_ends(stamps, 20.0, 0.1)
    assert ends[-1] == len(stamps) and ends == sorted(set(ends))
    lengths = np.diff([1, *ends])
    assert lengths[0] == 20 and lengths[:9].tolist() == [20] * 9  # 20 s until 200 s solved
    assert lengths[-2] >= 150  # 10 % of the time solved
    assert len(ends) < 40  # the prefix sizes add up to about 11 runs, not 100
    assert step_ends(stamps[:1], 20.0, 0.1) == []
    assert step_ends(stamps[:2], 20.0, 0.1) == [2]


def test_continuation_reaches_the_optimum_one_batch_solve_misses() -> None:
    """Odometry turning 0.04 rad too far every metre: from dead reckoning (more than 10 m
    off), one Levenberg-Marquardt solve stops in another basin; solved prefix by prefix from
    the same start, the run reaches the optimum the same solve finds from the true poses."""
    data, truth = corridor_loop()
    optimum = batch(data, truth)
    assert rms_error(dead_reckoning(data), truth) > 10.0
    assert rms_error(batch(data, dead_reckoning(data)), optimum) > 1.0
    poses, landmarks = incremental_least_squares(data, least_squares)
    assert rms_error(poses, optimum) < 0.05
    np.testing.assert_allclose(poses[0], data.prior_pose, atol=1e-9)
    assert sorted(landmarks) == sorted(set(data.obs_landmark_id.tolist()))


def test_a_run_without_landmarks_is_its_dead_reckoning() -> None:
    data, _ = corridor_loop()
    empty = dataclasses.replace(
        data,
        obs_keyframe=np.zeros(0, dtype=np.int64),
        obs_landmark_id=np.zeros(0, dtype=np.int64),
        obs_z=np.zeros((0, 2)),
        obs_cov=np.zeros((0, 2, 2)),
    )
    poses, landmarks = incremental_least_squares(empty, least_squares)
    np.testing.assert_allclose(poses, dead_reckoning(empty), atol=1e-12)
    assert landmarks == {}
