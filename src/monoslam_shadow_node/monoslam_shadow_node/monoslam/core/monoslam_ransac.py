"""The 1-point RANSAC EKF update of the MonoSLAM filter (Civera et al., J. Field Robotics 2010).

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import math

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_ekf import (
    Linearized,
    Match,
    UpdateOutcome,
    apply_update,
    gate_all,
    innovation_matrix,
    linearize_all,
    marginal_variance,
    matches,
    measurement_variance,
    probation_update,
    record_attempts,
    renormalize_quaternion,
    split_probation,
    stacked,
)
from monoslam_shadow_node.monoslam.core.monoslam_init import (
    MIN_KNOWN_POINTS,
    camera_from_known_points,
)
from monoslam_shadow_node.monoslam.core.monoslam_model import (
    CAMERA_SIZE,
    Q_SLICE,
    R_SLICE,
    beyond_fold,
    feature_directions,
)
from monoslam_shadow_node.monoslam.core.monoslam_state import FilterState
from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig, UpdateCounts
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import rotation_from_quaternion

RANSAC_PROBABILITY = 0.99
"""p: the probability that at least one hypothesis is drawn from an inlier (the paper's)."""


def ransac_update(
    state: FilterState,
    camera_model: CameraModel,
    observed: dict[int, FloatArray],
    known: list[tuple[FloatArray, FloatArray]],
    config: MonoSlamConfig,
    rng: np.random.Generator,
) -> UpdateOutcome:
    """Apply the 1-point RANSAC update; return what was measured and rejected, with the counts."""
    all_matches, on_probation = split_probation(matches(state, observed, known))
    compatible: list[tuple[int, Linearized]] = []
    linearized_all = linearize_all(state, camera_model, all_matches, config.second_order)
    gates = gate_all(all_matches, linearized_all, state.p, config)
    for index, linearized in enumerate(linearized_all):
        if linearized is not None and gates[index]:
            compatible.append((index, linearized))
    pairs = [(all_matches[index], linearized) for index, linearized in compatible]
    inliers, hypotheses = best_hypothesis(state, camera_model, pairs, config, rng)
    low = {compatible[k][0] for k in inliers}
    rescued: list[tuple[Match, Linearized]] = []
    rescued_indices: set[int] = set()
    others = [index for index, _ in compatible if index not in low]
    candidates = [all_matches[index] for index in others]
    judge = previewed(state, [pairs[k] for k in inliers], candidates, config)
    again = linearize_all(judge, camera_model, candidates, config.second_order)
    gates = gate_all(candidates, again, judge.p, config)
    for index, match, linearized, passed in zip(others, candidates, again, gates, strict=True):
        if linearized is not None and passed:
            rescued.append((match, linearized))
            rescued_indices.add(index)
    chosen = low | rescued_indices  # every inlier in one update from the prior
    apply_update(state, [(all_matches[i], lin) for i, lin in compatible if i in chosen], config)
    considered = probation_update(state, camera_model, on_probation, config)
    accepted = low | rescued_indices | {len(all_matches) + index for index in considered}
    outcome = record_attempts(all_matches + on_probation, accepted)
    counts = UpdateCounts(
        compatible=len(compatible),
        hypotheses=hypotheses,
        low_innovation_inliers=len(low),
        rescued=len(rescued),
        rejected=outcome.counts.rejected,
        probation=len(considered),
    )
    return UpdateOutcome(outcome.measured, outcome.rejected, outcome.known_used, counts)


def previewed(
    state: FilterState,
    used: list[tuple[Match, Linearized]],
    judged: list[Match],
    config: MonoSlamConfig,
) -> FilterState:
    """Return the state the update with ``used`` would leave, only where ``judged`` reads it."""
    out = FilterState()
    out.features, out.x, out.p = state.features, state.x.copy(), state.p
    if not used:
        return out
    h, residual, variances, columns, second_order = stacked(used, config)
    blocks = [np.arange(m.feature.start, m.feature.start + m.feature.extent)
              for m in judged if m.feature is not None]  # fmt: skip
    rows = np.unique(np.concatenate([np.arange(CAMERA_SIZE), *blocks]))
    ph_t = state.p[:, columns] @ h.T
    s_inverse = np.linalg.inv(innovation_matrix(h, ph_t[columns], variances, second_order))
    out.x = state.x + ph_t @ (s_inverse @ residual)
    sub = ph_t[rows]
    local = state.p[np.ix_(rows, rows)] - sub @ s_inverse @ sub.T
    quaternion = np.flatnonzero(np.isin(rows, np.arange(Q_SLICE.start, Q_SLICE.stop)))
    jacobian = np.eye(len(rows))
    jacobian[np.ix_(quaternion, quaternion)] = renormalize_quaternion(out.x)
    out.p = np.zeros_like(state.p)
    out.p[np.ix_(rows, rows)] = jacobian @ local @ jacobian.T
    return out


def best_hypothesis(
    state: FilterState,
    camera_model: CameraModel,
    compatible: list[tuple[Match, Linearized]],
    config: MonoSlamConfig,
    rng: np.random.Generator,
) -> tuple[IntArray, int]:
    """Return the best admissible hypothesis's low-innovation inliers (K,) and hypotheses tried."""
    best: IntArray = np.zeros(0, dtype=np.int64)
    count = len(compatible)
    if count == 0:
        return best, 0
    observed = np.array([match.pixel for match, _ in compatible])
    wanted = [match for match, _ in compatible]
    variances = np.array([measurement_variance(match, config) for match in wanted])
    # low_innovation_threshold_px, per match: about the point's projection, offset included
    threshold2 = config.gate * np.array([marginal_variance(match, config) for match in wanted])
    known = np.array([match.point is not None for match, _ in compatible], dtype=bool)
    anchored = int(np.count_nonzero(known)) >= MIN_KNOWN_POINTS

    def support(x: FloatArray) -> IntArray:
        predicted = predicted_pixels(camera_model, x, wanted)
        with np.errstate(invalid='ignore'):  # NaN behind the camera: never an inlier
            inside = np.sum((observed - predicted) ** 2, axis=1) <= threshold2
        return np.flatnonzero(inside).astype(np.int64)

    order = rng.permutation(count)
    needed = count
    tried = 0
    while tried < min(needed, count):
        index = int(order[tried])
        inliers = support(hypothesis_mean(state, *compatible[index], float(variances[index])))
        tried += 1
        if anchored and 2 * np.count_nonzero(known[inliers]) <= np.count_nonzero(known):
            continue  # it disagrees with the known points: not admissible (module docstring)
        if len(inliers) > len(best):
            best = inliers
            needed = hypotheses_needed(len(best) / count)
    if anchored and not len(best):  # none admissible: the pose the known points give
        points = np.array([match.point for match in wanted if match.point is not None])
        fix = camera_from_known_points(
            camera_model, points, observed[known], config.pixel_sigma_px
        )
        if fix is not None:
            x = state.x.copy()
            x[R_SLICE], x[Q_SLICE] = fix.centre, fix.pose_state[3:7]
            best = support(x)
            tried += 1
    return best, tried


def hypotheses_needed(inlier_ratio: float, probability: float = RANSAC_PROBABILITY) -> int:
    """Return n_hyp = ceil(log(1 - p) / log(1 - epsilon)), at least 1."""
    if inlier_ratio >= 1.0:
        return 1
    if inlier_ratio <= 0.0:
        raise ValueError(f'inlier ratio {inlier_ratio}: must be > 0')
    return max(1, math.ceil(math.log(1.0 - probability) / math.log(1.0 - inlier_ratio)))


def hypothesis_mean(
    state: FilterState, match: Match, linearized: Linearized, sigma2: float
) -> FloatArray:
    """Return the mean (n,) updated with one measurement alone (quaternion renormalized)."""
    p_h_t = linearized.p_h_t(state.p)
    s = linearized.innovation_covariance(state.p, sigma2)
    x = state.x + p_h_t @ np.linalg.solve(s, match.pixel - linearized.predicted)
    x[Q_SLICE] /= np.linalg.norm(x[Q_SLICE])
    return np.asarray(x, dtype=np.float64)


def predicted_pixels(camera_model: CameraModel, x: FloatArray, wanted: list[Match]) -> FloatArray:
    """Return the matches' pixels (M, 2) from the mean ``x``, offset states added (NaN: unseen)."""
    centre = x[R_SLICE]
    rotation_t = rotation_from_quaternion(x[Q_SLICE]).T
    points: list[tuple[FloatArray, FloatArray | None]] = []
    for match in wanted:
        if match.point is not None:
            points.append((match.point, None))
        elif (feature := match.feature) is not None:
            points.append((x[feature.start : feature.start + feature.size], feature.reference))
        else:
            raise ValueError('a match needs a known point or a feature')
    directions = feature_directions(points, centre)
    in_camera = directions @ rotation_t.T
    pixels = np.full((len(wanted), 2), np.nan)
    front = (in_camera[:, 2] > 0.0) & ~beyond_fold(camera_model, in_camera)
    if np.any(front):
        pixels[front] = camera_model.project(in_camera[front])
    for k, match in enumerate(wanted):  # a feature's tracker offset, if a state
        if match.feature is not None and (offset := match.feature.offset) is not None:
            pixels[k] += x[offset]
    return pixels
