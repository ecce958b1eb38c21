"""EM-SAM on a saved map: the static landmarks of an earlier session held fixed; see
docs/design/em_sam_core.md and docs/design/em_sam_localization.md."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from em_sam_node.core.assembly import MappingData, build_problem
from em_sam_node.core.em import _solve, anchored_problem, run_em
from em_sam_node.core.em_types import EmConfig, EmResult
from em_sam_node.core.em_weights import chi2_quantile, weight_model, with_noise_scales
from em_sam_node.core.marginals import joint_landmark_covariance, marginal_landmark_covariances
from em_sam_node.core.problem import Estimate
from em_sam_node.core.sightings import at_latest_sightings, sightings_of
from slam_core.arrays import FloatArray, IntArray
from slam_core.geometry.se2 import (
    between,
    compose,
    rotation_matrices,
    transform_points,
    wrap_angle,
)

SESSION_PRIOR_COV = np.diag([1e-6, 1e-6, 1e-6])
"""The session's own frame is its first pose (mapping's default prior, 1 mm and 1 mrad)."""


@dataclass(frozen=True)
class KnownMap:
    """A saved map's static landmarks: ids (S,), positions (S, 2) m, covariances (S, 2, 2) m^2."""

    landmark_ids: IntArray
    positions: FloatArray
    covariances: FloatArray
    joint: FloatArray | None = None
    """The joint covariance (2S, 2S) of the positions, when the map holds it (the errors of
    a map are correlated: a stretch of it is off together)."""

    def __post_init__(self) -> None:
        count = len(self.landmark_ids)
        if self.joint is not None and self.joint.shape != (2 * count, 2 * count):
            raise ValueError(f'saved map: joint covariance {self.joint.shape} for {count} ids')
        if self.positions.shape != (count, 2) or self.covariances.shape != (count, 2, 2):
            raise ValueError(
                f'saved map: {count} ids, positions {self.positions.shape}, covariances '
                f'{self.covariances.shape}; expected (S, 2) and (S, 2, 2)'
            )
        if len(np.unique(self.landmark_ids)) != count:
            raise ValueError('saved map: a landmark id appears twice')
        if not (np.all(np.isfinite(self.positions)) and np.all(np.isfinite(self.covariances))):
            raise ValueError('saved map: positions and covariances must be finite')


@dataclass(frozen=True)
class Registration:
    """The session frame in the map frame (x m, y m, theta rad); per common landmark its
    squared Mahalanobis distance, weight, moved flag and residual covariance (2, 2) m^2."""

    pose: FloatArray
    ids: IntArray
    distances: FloatArray
    weights: FloatArray
    moved: np.ndarray
    consistent: int
    spreads: FloatArray


def _fit(points: FloatArray, targets: FloatArray) -> FloatArray:
    """The rigid transform (x, y, theta) taking ``points`` (n, 2) onto ``targets``."""
    mean_p, mean_t = points.mean(axis=0), targets.mean(axis=0)
    a, b = points - mean_p, targets - mean_t
    angle = float(np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b)))
    return np.array([*(mean_t - rotation_matrices(angle) @ mean_p), angle])


def _jacobian(pose: FloatArray, points: FloatArray) -> FloatArray:
    """d(R p + t)/d(x, y, theta) (2m, 3) at each point, x then y of each in turn."""
    rotated = points @ rotation_matrices(float(pose[2])).T
    jacobian = np.zeros((len(points), 2, 3))
    jacobian[:, 0, 0] = jacobian[:, 1, 1] = 1.0
    jacobian[:, 0, 2], jacobian[:, 1, 2] = -rotated[:, 1], rotated[:, 0]
    return jacobian.reshape(2 * len(points), 3)


GAUGE_COVARIANCE = np.diag([1e4, 1e4, 1e2])
"""The registration's transform as a random variable with this covariance (100 m, 100 m,
10 rad: unknown) added to the residuals' covariance, so that conditioning on the consistent
landmarks also fits the transform."""


def _leave_one_out(
    residual: FloatArray, covariance: FloatArray, inliers: np.ndarray
) -> tuple[FloatArray, FloatArray]:
    """Each landmark's squared Mahalanobis distance (m,) given the consistent ones, and the
    covariance (m, 2, 2) it is measured with."""
    count = len(inliers)
    rows = np.repeat(inliers, 2)
    held = np.flatnonzero(rows)
    precision = np.linalg.inv(covariance[np.ix_(held, held)])
    weighted = precision @ residual[held]
    distances, spreads = np.empty(count), np.empty((count, 2, 2))
    position = {int(v): k for k, v in enumerate(held.tolist())}
    for i in range(count):
        own = np.array([2 * i, 2 * i + 1])
        if inliers[i]:
            at = np.array([position[2 * i], position[2 * i + 1]])
            spread = np.linalg.inv(precision[np.ix_(at, at)])
            innovation = spread @ weighted[at]
        else:
            cross = covariance[np.ix_(own, held)]
            spread = covariance[np.ix_(own, own)] - cross @ precision @ cross.T
            innovation = residual[own] - cross @ weighted
        spreads[i] = spread
        distances[i] = float(innovation @ np.linalg.solve(spread, innovation))
    return distances, spreads


def register(
    config: EmConfig,
    session: EmResult,
    joint: FloatArray,
    saved: KnownMap,
    start_pose: FloatArray,
) -> Registration:
    """Register the session's static landmarks to the saved map, testing each leave-one-out.

    ``joint`` (2S, 2S) m^2: the session's joint covariance of the common landmarks.
    """
    static = ~session.moveable & np.isin(session.landmark_ids, saved.landmark_ids)
    ids = session.landmark_ids[static]
    order = np.argsort(saved.landmark_ids)
    index = order[np.searchsorted(saved.landmark_ids[order], ids)]
    points, targets = session.positions[static], saved.positions[index]
    count = len(ids)
    gate = chi2_quantile(1.0 - config.false_alarm_probability, 2)
    if count < 2:
        return _unregistered(start_pose, ids)
    rows = (2 * index[:, None] + np.arange(2)).ravel()
    if saved.joint is not None:
        saved_joint = saved.joint[np.ix_(rows, rows)]
    else:
        saved_joint = np.zeros((2 * count, 2 * count))
        for k, j in enumerate(index.tolist()):
            saved_joint[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = saved.covariances[j]
    model = weight_model(config).model_variance_m2()
    inliers = np.ones(count, dtype=bool)
    while True:
        pose = _fit(points[inliers], targets[inliers])  # the consistent ones' transform
        turn = np.kron(np.eye(count), rotation_matrices(float(pose[2]))).astype(np.float64)
        jacobian = _jacobian(pose, points)
        covariance = (
            saved_joint
            + turn @ joint @ turn.T
            + model * np.eye(2 * count)
            + jacobian @ GAUGE_COVARIANCE @ jacobian.T
        )
        residual = (targets - transform_points(pose, points)).ravel()
        distances, spreads = _leave_one_out(residual, covariance, inliers)
        worst = int(np.argmax(np.where(inliers, distances, -np.inf)))
        if distances[worst] < gate or inliers.sum() <= 2:
            break
        inliers[worst] = False
    excess = np.maximum(distances - 2.0, 0.0)
    weights = np.clip(1.0 - excess / (2.0 * (gate - 2.0)), 0.0, 1.0)
    pose = np.array([pose[0], pose[1], wrap_angle(float(pose[2]))])
    moved = weights < config.moveable_threshold
    return Registration(pose, ids, distances, weights, moved, int((~moved).sum()), spreads)


def _unregistered(start_pose: FloatArray, ids: IntArray) -> Registration:
    """Too few common landmarks: the session at its start pose, nothing moved."""
    count = len(ids)
    return Registration(
        np.asarray(start_pose, dtype=float), ids, np.zeros(count), np.ones(count),
        np.zeros(count, dtype=bool), 0, np.zeros((count, 2, 2)),
    )  # fmt: skip


def run_localization(
    data: MappingData,
    saved: KnownMap,
    config: EmConfig,
    *,
    initial_poses: FloatArray | None = None,
    on_iteration: Callable[[int, FloatArray], None] | None = None,
) -> EmResult:
    """EM-SAM of ``data`` on the ``saved`` static map (``localize``'s result)."""
    return localize(data, saved, config, initial_poses=initial_poses, on_iteration=on_iteration)[0]


def localize(
    data: MappingData,
    saved: KnownMap,
    config: EmConfig,
    *,
    initial_poses: FloatArray | None = None,
    on_iteration: Callable[[int, FloatArray], None] | None = None,
) -> tuple[EmResult, Registration]:
    """EM-SAM of ``data`` on the ``saved`` static map, and how the session was registered.

    ``initial_poses`` (N, 3), map frame, warm-start the session's solve.
    """
    started = time.perf_counter()
    start_pose = np.asarray(data.prior_pose, dtype=float)
    # 1. the session alone, in the frame of its first keyframe
    local = dataclasses.replace(data, prior_pose=np.zeros(3), prior_cov=SESSION_PRIOR_COV)
    warm = None
    if initial_poses is not None:
        warm = between(initial_poses[0], initial_poses)
    session = run_em(
        local, config, initial_poses=warm, record_snapshots=False, on_iteration=on_iteration
    )
    timings = {'session': time.perf_counter() - started}
    # 2. between the sessions
    _, joint = static_joint_covariance(local, session, saved.landmark_ids)
    registration = register(config, session, joint, saved, start_pose)
    moved_ids = registration.ids[registration.moved]
    moveable = session.moveable | np.isin(session.landmark_ids, moved_ids)
    weights = session.weights.copy()
    common = np.searchsorted(session.landmark_ids, registration.ids)
    weights[common] = np.minimum(weights[common], registration.weights)
    # 3. on the saved map
    fixed_ids = saved.landmark_ids[~np.isin(saved.landmark_ids, moved_ids)]
    moveable_ids = session.landmark_ids[moveable]
    if np.any(session.final_noise_scale > 1.0):  # the sensor model the session estimated
        data = with_noise_scales(data, session.final_noise_scale)
    poses0 = compose(registration.pose, session.poses)
    # the start's prior where the registration put it (the saved map anchors the rest)
    data = dataclasses.replace(data, prior_pose=poses0[0])
    static = build_problem(data, exclude_ids=moveable_ids.tolist())
    problem, pieces = anchored_problem(static, poses0)
    fixed = np.isin(static.landmark_ids, fixed_ids)
    problem = dataclasses.replace(problem, fixed_landmarks=fixed)
    in_session = np.searchsorted(session.landmark_ids, static.landmark_ids)
    landmarks = transform_points(registration.pose, session.positions[in_session])
    saved_order = np.argsort(saved.landmark_ids)
    saved_at = saved_order[
        np.searchsorted(saved.landmark_ids[saved_order], static.landmark_ids[fixed])
    ]
    landmarks[fixed] = saved.positions[saved_at]
    positions = transform_points(registration.pose, session.positions)
    rotation = rotation_matrices(float(registration.pose[2]))
    covariances = rotation @ session.covariances @ rotation.T
    if problem.num_landmarks:
        solved = _solve(
            config,
            problem,
            Estimate(poses0, landmarks),
            robust_kernel=weight_model(config).final_kernel(),
        )
        estimated = marginal_landmark_covariances(problem, solved)
        positions[in_session] = solved.landmarks
        covariances[in_session] = estimated
        covariances[in_session[fixed]] = saved.covariances[saved_at]
    else:
        solved = Estimate(poses0, np.zeros((0, 2)))
    sightings = sightings_of(data, problem, solved, moveable_ids.tolist())
    at_latest_sightings(sightings, session.landmark_ids, moveable, positions, covariances)
    timings['total'] = time.perf_counter() - started
    unseen = ~np.isin(saved.landmark_ids, session.landmark_ids)
    extra = int(unseen.sum())
    ids = np.concatenate([session.landmark_ids, saved.landmark_ids[unseen]])
    order = np.argsort(ids, kind='stable')
    history = np.vstack([session.weight_history, weights[None]])
    result = dataclasses.replace(
        session,
        poses=solved.poses,
        landmark_ids=ids[order],
        positions=np.concatenate([positions, saved.positions[unseen]])[order],
        covariances=np.concatenate([covariances, saved.covariances[unseen]])[order],
        weights=np.concatenate([weights, np.ones(extra)])[order],
        moveable=np.concatenate([moveable, np.zeros(extra, dtype=bool)])[order],
        num_observations=np.concatenate(
            [session.num_observations, np.zeros(extra, dtype=np.int64)]
        )[order],
        weight_history=np.hstack([history, np.ones((len(history), extra))])[:, order],
        sightings=sightings,
        num_pieces=max(session.num_pieces, pieces),
        timings_s={**session.timings_s, **timings},
        odometry_calibration=session.odometry_calibration,
    )
    return result, registration


def static_joint_covariance(
    data: MappingData, result: EmResult, among: IntArray | None = None
) -> tuple[IntArray, FloatArray]:
    """The ids (S,) and joint covariance (2S, 2S) m^2 of a mapping ``result``'s static
    landmarks (those in ``among``, when given)."""
    if np.any(result.final_noise_scale > 1.0):
        data = with_noise_scales(data, result.final_noise_scale)
    static = build_problem(data, exclude_ids=result.landmark_ids[result.moveable].tolist())
    keep = np.isin(result.landmark_ids, static.landmark_ids)
    problem, _ = anchored_problem(static, result.poses)
    estimate = Estimate(result.poses, result.positions[keep])
    chosen = np.arange(len(static.landmark_ids))
    if among is not None:
        chosen = np.flatnonzero(np.isin(static.landmark_ids, among))
    if len(chosen) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 0))
    return static.landmark_ids[chosen], joint_landmark_covariance(problem, estimate, chosen)
