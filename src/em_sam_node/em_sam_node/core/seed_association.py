"""The robust seed's association: which mapped cluster a new step's sightings belong to;
see docs/design/em_sam_core.md."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from em_sam_node.core.assembly import MappingData, dead_reckoning
from em_sam_node.core.consensus import IDENTITY, Correction, consensus
from em_sam_node.core.continuation import prefix
from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.em_weights import weight_model
from em_sam_node.core.factorization import factorize, hold_uninformed
from em_sam_node.core.factors import (
    odometry_residuals,
    range_bearing_error,
    range_bearing_error_jacobians,
)
from em_sam_node.core.linear_system import linearize_factors, normal_equations, system_layout
from em_sam_node.core.problem import Estimate, SlamProblem
from em_sam_node.core.sightings import sighting_jacobians
from slam_core.arrays import FloatArray, IntArray
from slam_core.geometry.se2 import between, range_bearing_to_point, wrap_angle
from slam_core.lazy_stats import chi2

# Stretches of the step's length the solved prefix must hold before the drift it shows can
# refuse a consensus correction (before, most landmarks agreeing is enough).
MIN_DRIFT_STRETCHES = 3


@dataclass(frozen=True)
class SolvedStep:
    """The previous step's problem, solution and row scales (for predicted covariances)."""

    problem: SlamProblem
    estimate: Estimate
    rows: FloatArray
    ids: list[int]

    @property
    def odometry_factor(self) -> float:
        """The odometry's a-posteriori variance factor (>= 1): mean squared whitened residual."""
        residuals = odometry_residuals(self.problem, self.estimate)
        if residuals.size == 0:
            return 1.0
        return max(1.0, float(np.mean(residuals**2)))


def _prefix_covariances(
    solved: SolvedStep, last: int, wanted_ids: list[int]
) -> tuple[FloatArray, dict[int, FloatArray], dict[int, FloatArray]]:
    """Marginal (3, 3) of pose ``last``; per id in ``wanted_ids`` its marginal (2, 2) and
    cross-covariance (2, 3) with that pose."""
    problem, estimate = solved.problem, solved.estimate
    layout = system_layout(problem)
    data, _ = normal_equations(layout, linearize_factors(problem, estimate, solved.rows))
    hold_uninformed(layout, data)
    factor = factorize(layout, data, check_rank=False)
    pose_vars = 3 * last + np.arange(3)
    index_of = {landmark_id: index for index, landmark_id in enumerate(solved.ids)}
    indices = np.array([index_of[i] for i in wanted_ids], dtype=np.int64)
    landmark_vars = (3 * problem.num_poses + 2 * indices[:, None] + np.arange(2)).ravel()
    wanted = np.concatenate([pose_vars, landmark_vars])
    rhs = np.zeros((layout.num_variables, wanted.size))
    rhs[wanted, np.arange(wanted.size)] = 1.0
    columns = factor.solve(rhs)  # (n, 3 + 2L)
    pose_cov = columns[pose_vars][:, :3]
    marginal, cross = {}, {}
    for n, (landmark_id, index) in enumerate(zip(wanted_ids, indices.tolist(), strict=True)):
        rows = 3 * problem.num_poses + 2 * index + np.arange(2)
        marginal[landmark_id] = columns[rows][:, 3 + 2 * n : 5 + 2 * n]
        cross[landmark_id] = columns[rows][:, :3]
    return 0.5 * (pose_cov + pose_cov.T), marginal, cross


def chunks(stamps_ns: IntArray, done: int, count: int, chunk_s: float) -> list[tuple[int, int]]:
    """Keyframes [done, count) cut into spans of at most ``chunk_s`` (at least one keyframe)."""
    chunks = []
    begin = done
    while begin < count:
        limit = stamps_ns[begin] + int(chunk_s * 1e9)
        end = int(np.searchsorted(stamps_ns[:count], limit, side='right'))
        end = min(max(end, begin + 1), count)
        chunks.append((begin, end))
        begin = end
    return chunks


@dataclass
class Prediction:
    """A step's predicted uncertainty (poses (3, 3), clusters (2, 2) and (2, 3)), and the
    clusters first seen in the step so far."""

    pose_cov: FloatArray
    marginal: dict[int, FloatArray]
    cross: dict[int, FloatArray]
    covs: dict[int, FloatArray]
    within: dict[int, FloatArray]
    transfer: dict[int, FloatArray]
    known_drift: bool
    anchor: dict[int, int] = field(default_factory=dict)
    placed: dict[int, FloatArray] = field(default_factory=dict)


def predict_step(
    data: MappingData,
    virtual_ids: IntArray,
    origin: dict[int, int],
    poses: FloatArray,
    span: tuple[int, int],
    mapped: dict[int, FloatArray],
    solved: SolvedStep,
) -> Prediction:
    """The predicted uncertainty of keyframes [done, count) of ``span`` extended from the
    solved prefix (first order)."""
    done, count = span
    rows = np.flatnonzero((data.obs_keyframe >= done) & (data.obs_keyframe < count))
    seen_origins = {origin[int(c)] for c in np.unique(virtual_ids[rows]).tolist()}
    wanted = sorted(v for v in mapped if origin[v] in seen_origins)
    pose_cov, marginal, cross = _prefix_covariances(solved, done - 1, wanted)
    factor = solved.odometry_factor
    drift_rate = _drift_covariance_per_keyframe(data, solved.estimate.poses, count - done)
    incoming = {int(t): m for m, t in enumerate(data.odometry_to.tolist())}
    covs = {done - 1: pose_cov}
    within = {done - 1: np.zeros((3, 3))}  # the odometry model's own growth in the step
    transfer = {done - 1: np.eye(3)}  # d pose_k / d pose_last
    for k in range(done, count):
        m = incoming.get(k)
        if m is None or data.odometry_from[m] != k - 1:
            covs[k], transfer[k] = covs[k - 1] + np.diag([1e6, 1e6, 1e6]), transfer[k - 1] * 0
            within[k] = within[k - 1] + np.diag([1e6, 1e6, 1e6])
            continue
        u = data.odometry_u[m]
        heading = poses[k - 1, 2] + 0.5 * u[2]
        c, s = np.cos(heading), np.sin(heading)
        dx, dy = c * u[0] - s * u[1], s * u[0] + c * u[1]
        f = np.array([[1.0, 0.0, -dy], [0.0, 1.0, dx], [0.0, 0.0, 1.0]])
        g = np.array([[c, -s, -0.5 * dy], [s, c, 0.5 * dx], [0.0, 0.0, 1.0]])
        covs[k] = f @ covs[k - 1] @ f.T + factor * (g @ data.odometry_cov[m] @ g.T)
        covs[k] = covs[k] + _rotate(drift_rate, poses[k - 1, 2])
        within[k] = f @ within[k - 1] @ f.T + g @ data.odometry_cov[m] @ g.T
        transfer[k] = f @ transfer[k - 1]
    known_drift = done >= MIN_DRIFT_STRETCHES * (count - done)
    prediction = Prediction(pose_cov, marginal, cross, covs, within, transfer, known_drift)
    prediction.anchor = dict.fromkeys(wanted, done - 1)
    return prediction


def map_in_step(
    data: MappingData,
    virtual_ids: IntArray,
    poses: FloatArray,
    chunk: tuple[int, int],
    mapped: dict[int, FloatArray],
    prediction: Prediction,
) -> None:
    """Place the clusters first seen in ``chunk`` at the median of their sightings, with the
    predicted covariance of their first sighting."""
    begin, end = chunk
    rows = np.flatnonzero((data.obs_keyframe >= begin) & (data.obs_keyframe < end))
    for cluster in np.unique(virtual_ids[rows]).tolist():
        if cluster in mapped or cluster in prediction.placed:
            continue
        mine = rows[virtual_ids[rows] == cluster]
        first = int(mine[np.argmin(data.obs_keyframe[mine])])
        k = int(data.obs_keyframe[first])
        points = range_bearing_to_point(poses[data.obs_keyframe[mine]], data.obs_z[mine])
        j_poses, j_zs = sighting_jacobians(poses[k][None], data.obs_z[first][None])
        j_pose, j_z = j_poses[0], j_zs[0]
        prediction.placed[cluster] = np.median(points, axis=0)
        prediction.marginal[cluster] = (
            j_pose @ prediction.covs[k] @ j_pose.T + j_z @ data.obs_cov[first] @ j_z.T
        )
        prediction.cross[cluster] = j_pose @ prediction.covs[k]
        prediction.anchor[cluster] = k


def associate(
    config: EmConfig,
    data: MappingData,
    virtual_ids: IntArray,
    origin: dict[int, int],
    poses: FloatArray,
    span: tuple[int, int],
    mapped: dict[int, FloatArray],
    prediction: Prediction,
    placed_only: bool,
) -> tuple[dict[int, tuple[int | None, int]], bool]:
    """Which cluster the sightings in keyframes [begin, end) belong to, by cluster id:
    (compatible cluster or None when it moved, first keyframe); and whether to graduate."""
    begin, end = span
    rows = np.flatnonzero((data.obs_keyframe >= begin) & (data.obs_keyframe < end))
    known = {**mapped, **prediction.placed}
    rows = rows[np.isin(virtual_ids[rows], list(prediction.placed if placed_only else mapped))]
    if len(rows) == 0:
        return {}, True
    rows = rows[np.argsort(data.obs_keyframe[rows], kind='stable')]
    # The drift consensus is over clusters the prefix mapped: those placed in this step
    # came through the extended poses and agree with them by construction.
    voting = np.isin(virtual_ids[rows], list(mapped))
    covs, within = prediction.covs, prediction.within
    keyframes = data.obs_keyframe[rows]
    landmark_ids = virtual_ids[rows]
    sighting_cov = data.obs_cov[rows]
    test_cov = weight_model(config).test_covariances(sighting_cov, data.obs_z[rows])
    if test_cov is not None:
        sighting_cov = test_cov
    # How far the odometry model lets each sighting's pose drift since the step began, as
    # a position variance at its range: the part of the drift one rigid correction of the
    # chunk cannot take out.
    growth = np.array([within[k] for k in keyframes.tolist()])
    drift_variance = (
        0.5 * (growth[:, 0, 0] + growth[:, 1, 1]) + data.obs_z[rows, 0] ** 2 * (growth[:, 2, 2])
    )
    correction, agreed = IDENTITY, set[int]()
    if np.any(voting):
        correction, agreed = _drift_consensus(
            config,
            poses[keyframes[voting]],
            data.obs_z[rows[voting]],
            data.obs_cov[rows[voting]],
            np.maximum(drift_variance[voting], 0.0),
            landmark_ids[voting],
            mapped,
        )
    shift = correction.apply_poses(poses[end - 1 :])[0] - poses[end - 1]
    shift[2] = wrap_angle(float(shift[2]))
    plausible = chi2.ppf(1.0 - config.false_alarm_probability, 3)
    if prediction.known_drift and shift @ np.linalg.solve(covs[end - 1], shift) > plausible:
        agreed = set()  # the odometry, as far as it drifted before, is not that far off
    gate = chi2.ppf(1.0 - config.false_alarm_probability, 2)
    decisions: dict[int, tuple[int | None, int]] = {}
    for current in np.unique(landmark_ids).tolist():
        if current in agreed:
            decisions[current] = (current, begin)
            continue
        mine = landmark_ids == current
        sightings = (data.obs_z[rows[mine]], keyframes[mine], sighting_cov[mine])
        best, best_distance = None, gate
        others = [c for c in prediction.anchor if origin[c] == origin[current]]
        if agreed and current in mapped:  # a consensus fixed the stretch, this is outside it
            others = [c for c in others if c != current]
        here = None
        for candidate in others:
            distances = _distances(poses, prediction, candidate, sightings, known[candidate])
            if candidate == current:
                here = distances
            if float(np.median(distances)) <= best_distance:
                best, best_distance = candidate, float(np.median(distances))
        first = begin
        if best != current and here is not None:
            leading = int(np.argmax(np.append(here > gate, True)))
            first = int(keyframes[mine][leading]) if leading < len(here) else end
        decisions[current] = (best, first)
    no_drift = bool(agreed) and correction.angle == 0.0 and not np.any(correction.translation)
    return decisions, not no_drift


def _distances(
    poses: FloatArray,
    prediction: Prediction,
    cluster: int,
    sightings: tuple[FloatArray, IntArray, FloatArray],
    position: FloatArray,
) -> FloatArray:
    """Squared Mahalanobis distances (n,) of sightings z (n, 2) to a cluster at ``position``
    (2,), with the innovation covariance H P H^T + R."""
    z, keyframes, sighting_cov = sightings
    marginal, cross = prediction.marginal[cluster], prediction.cross[cluster]
    # cov(pose_k, l) = d pose_k / d pose_anchor cov(pose_anchor, l)
    # (pinv: across an odometry gap the transfer is zero and the correlation is lost).
    from_anchor = np.linalg.pinv(prediction.transfer[prediction.anchor[cluster]])
    positions = np.repeat(position[None], len(z), axis=0)
    innovation = range_bearing_error(poses[keyframes], positions, z)
    h_pose, h_landmark = range_bearing_error_jacobians(poses[keyframes], positions)
    distance = np.empty(len(z))
    for n, k in enumerate(keyframes.tolist()):
        pose_landmark = prediction.transfer[k] @ from_anchor @ cross.T  # (3,2)
        joint = np.block([[prediction.covs[k], pose_landmark], [pose_landmark.T, marginal]])
        h = np.hstack([h_pose[n], h_landmark[n]])
        predicted = h @ joint @ h.T + sighting_cov[n]
        distance[n] = innovation[n] @ np.linalg.solve(predicted, innovation[n])
    return distance


def _rotate(covariance: FloatArray, heading: float) -> FloatArray:
    """A pose-frame covariance (3,3) expressed in the map frame at ``heading``."""
    c, s = np.cos(heading), np.sin(heading)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    result: FloatArray = rotation @ covariance @ rotation.T
    return result


def _drift_covariance_per_keyframe(
    data: MappingData, solved: FloatArray, length: int
) -> FloatArray:
    """How far the odometry drifted from the solution, per keyframe (3, 3), pose frame."""
    count = len(solved)
    length = min(length, count - 1)
    if length < 1:
        return np.zeros((3, 3))
    odometry = dead_reckoning(prefix(data, count))
    starts = np.arange(0, count - length, max(1, length // 2))
    if len(starts) == 0:
        return np.zeros((3, 3))
    ends = starts + length
    # Relative poses in the stretch's start frame: the eq. 2 form is expressed at the
    # mid-heading, which turns by pi between two stretches that both turn about pi.
    reported = between(odometry[starts], odometry[ends])
    solved_motion = between(solved[starts], solved[ends])
    difference = reported - solved_motion
    difference[:, 2] = wrap_angle(difference[:, 2])
    result: FloatArray = difference.T @ difference / (len(starts) * length)
    return result


def _drift_consensus(
    config: EmConfig,
    poses: FloatArray,
    z: FloatArray,
    sighting_cov: FloatArray,
    drift_variance: FloatArray,
    landmark_ids: IntArray,
    mapped: dict[int, FloatArray],
) -> tuple[Correction, set[int]]:
    """The rigid correction most mapped landmarks seen in a step agree on, and those ids."""
    points = range_bearing_to_point(poses, z)
    ids = np.unique(landmark_ids).tolist()
    seen = np.array([np.median(points[landmark_ids == i], axis=0) for i in ids])
    target = np.array([mapped[int(i)] for i in ids])
    sigma = np.empty(len(ids))
    for n, landmark_id in enumerate(ids):
        mine = landmark_ids == landmark_id
        range_m = float(np.median(z[mine, 0]))
        variance = np.median(sighting_cov[mine, 0, 0]) + range_m**2 * np.median(
            sighting_cov[mine, 1, 1]
        )
        # The vote is the median of n sightings: pi/2 / n of one sighting's variance. A
        # landmark's own bias (model_error_m, see core.em_weights) does not average out.
        sigma[n] = np.sqrt(
            config.model_error_m**2
            + 0.5 * np.pi * variance / np.count_nonzero(mine)
            + float(np.median(drift_variance[mine]))
        )
    correction, mask = consensus(seen, target, sigma, config.false_alarm_probability)
    return correction, {int(i) for i, agree in zip(ids, mask, strict=True) if agree}
