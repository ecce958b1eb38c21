"""Viewing rays as uncertain Pluecker lines, and the three-ray test of paper 001 (III-A).

A feature seen from camera centre C (world frame) along the unit direction d is the line
L = X ^ D = Pi(X) D through the finite point X = (C, 1) and the point at infinity D = (d, 0)
(eq. 6-7). Its covariance comes from the pixel noise (through the undistorted ray) and, when
the camera pose is uncertain, from the pose covariance (position and rotation jointly, eq. 11).

Three rays of one static feature meet in one point. ``three_ray_test`` tests that relation,
which has three degrees of freedom (two lines meeting: 1; the third passing through their
meeting point: 2), with one distance vector d (5,):

1. d_a = L1 . Dual(L3), zero when rays 1 and 3 are coplanar (they meet);
2. X13 = L1 n A, where A = N ^ L3 is the plane through ray 3 and N = (d1 x d3, 0), the
   direction of the common perpendicular: X13 is the point of ray 1 nearest to ray 3;
3. d_b = O(L2) X13 (the plane through X13 and ray 2), zero when ray 2 passes through X13.

Every step is bilinear, so the Jacobians of d with respect to the three lines are products of
construction matrices; Sigma_dd = sum_i J_i Sigma_Li J_i' (the rays of different images are
independent given the camera poses, unless the tracker's offsets persist between them:
``tracking_noise``, whose cross terms J_i Sigma_LiLj J_j' are then added) and
T = d' Sigma_dd^+ d with the pseudo-inverse at rank 3 is compared with chi-square(3)
(``projective.relation_test``).

Coordinates are conditioned first (Heuel): centred on the middle camera and scaled by the
baseline between the first and last camera, so the homogeneous entities are of unit size; the
lines are spherically normalized. T does not depend on this to first order; it only keeps
the arithmetic well conditioned.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from monoslam_shadow_node.common.core.projective import (
    RANK_TOLERANCE,
    RelationTest,
    chi2_quantile,
    join_point_line,
    join_points,
    line_coplanarity,
    meet_line_plane,
    normalized,
    o_bar_matrix,
    o_matrix,
    pseudo_inverse_at_rank,
    relation_test,
)
from monoslam_shadow_node.common.core.tracking_noise import TrackingNoise
from slam_core.arrays import FloatArray
from slam_core.geometry.so3 import skew

THREE_RAY_DOF = 3


@dataclass(eq=False)
class View:
    """One sighting of a feature, everything in the world frame (a record the Shadow filter
    makes for every feature in every frame: not frozen, which costs a fifth to build).

    ``centre`` (3,) m is the camera centre, ``direction`` (3,) the unit viewing ray,
    ``direction_covariance`` (3, 3) its covariance from the pixel noise alone (rank 2),
    ``pose_covariance`` (6, 6) the camera pose covariance over (position m, rotation rad about
    the world axes) as in geometry_msgs/PoseWithCovariance, or None for a known pose.
    ``frame`` is the index of the image the feature was seen in. ``pixel_jacobian`` (3, 2)
    is d(direction)/d(pixel), which the correlated tracking offsets need (None: not known,
    the view's errors are taken as independent of every other view's). ``pose_cross`` maps
    the stamps of earlier poses to the covariance (6, 6) of this pose's error with theirs
    (``pose_links``; None or missing stamps: independent).
    """

    frame: int
    stamp_ns: int
    centre: FloatArray
    direction: FloatArray
    direction_covariance: FloatArray
    pose_covariance: FloatArray | None = None
    pixel_jacobian: FloatArray | None = None
    pose_cross: Mapping[int, FloatArray] | None = None


@dataclass(frozen=True, eq=False)
class UncertainLine:
    """A line L (6,) in Pluecker coordinates with its covariance (6, 6) and its Jacobian
    (6, 3) with respect to the viewing direction it was built from."""

    line: FloatArray
    covariance: FloatArray
    direction_jacobian: FloatArray


@dataclass(frozen=True, eq=False)
class ThreeRayTest:
    """The outcome of one three-ray test.

    ``result`` is the relation test; ``frames`` the three views' image indices;
    ``parallax_rad`` the angle between the outer rays; ``baseline_m`` the distance between the
    outer camera centres; ``point`` (3,) the world point where ray 1 passes nearest to ray 3
    (NaN if the rays are parallel). ``motion_noncentrality`` (3,) is what a feature moving at
    1 m/s would add to T's expectation (its noncentrality, scaling with speed squared) along
    the three principal directions of motion, least visible first (None when no position was
    given): how well this geometry could see motion at all (see ``three_ray_test``).
    """

    result: RelationTest
    frames: tuple[int, int, int]
    parallax_rad: float
    baseline_m: float
    point: FloatArray
    motion_noncentrality: FloatArray | None = None


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """a x b for two 3-vectors (np.cross costs ~10 us per call on 3-vectors; this ~1 us)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def ray_angle(first: FloatArray, second: FloatArray) -> float:
    """Return the angle (rad) between two unit directions."""
    return math.atan2(float(np.linalg.norm(_cross(first, second))), float(np.dot(first, second)))


def viewing_line(view: View, origin: FloatArray, scale: float) -> UncertainLine:
    """Return the view's ray as an uncertain line in conditioned coordinates
    ((x - origin) * scale), spherically normalized.

    L = Pi(X) D with X = (C', 1) and D = (d, 0). The joint covariance of (X, D) (8, 8) holds
    the centre's covariance (scaled), the direction's from the pixel noise and from the
    camera rotation (d = exp([dtheta]x) R r: dd = -[d]x dtheta) and their cross terms from
    the pose covariance; eq. 11 propagates it with [dL/dX, dL/dD] = [-Pi(D), Pi(X)].
    """
    centre = (view.centre - origin) * scale
    point = np.append(centre, 1.0)
    infinity = np.append(view.direction, 0.0)
    line, jac_point, jac_infinity = join_points(point, infinity)
    joint = np.zeros((8, 8))
    joint[4:7, 4:7] = view.direction_covariance
    if view.pose_covariance is not None:
        pose = np.asarray(view.pose_covariance, dtype=np.float64)
        d_direction = -skew(view.direction)  # d(direction) / d(rotation)
        joint[:3, :3] = scale * scale * pose[:3, :3]
        cross = scale * pose[:3, 3:] @ d_direction.T
        joint[:3, 4:7] = cross
        joint[4:7, :3] = cross.T
        joint[4:7, 4:7] += d_direction @ pose[3:, 3:] @ d_direction.T
    jacobian = np.hstack([jac_point, jac_infinity])  # (6, 8)
    covariance = jacobian @ joint @ jacobian.T
    unit, jac_unit = normalized(line)
    return UncertainLine(unit, jac_unit @ covariance @ jac_unit.T, jac_unit @ jac_infinity[:, :3])


def viewing_lines(
    views: list[View], origins: FloatArray, scales: FloatArray
) -> list[UncertainLine]:
    """Return ``viewing_line`` of every view (N) at once, view i conditioned with
    ``origins[i]`` (3,) and ``scales[i]``: the same algebra on stacked arrays."""
    count = len(views)
    directions = np.array([view.direction for view in views])
    centres = (np.array([view.centre for view in views]) - origins) * scales[:, None]
    d0, d1, d2 = directions[:, 0], directions[:, 1], directions[:, 2]
    c0, c1, c2 = centres[:, 0], centres[:, 1], centres[:, 2]
    # L = Pi(X) D = (d, C' x d); dL/dX = -Pi(D), dL/dD = Pi(X) (projective.pi_matrix)
    jacobian = np.zeros((count, 6, 8))
    jacobian[:, 0, 3], jacobian[:, 1, 3], jacobian[:, 2, 3] = d0, d1, d2
    jacobian[:, 3, 1], jacobian[:, 3, 2] = d2, -d1
    jacobian[:, 4, 0], jacobian[:, 4, 2] = -d2, d0
    jacobian[:, 5, 0], jacobian[:, 5, 1] = d1, -d0
    jacobian[:, 0, 4] = jacobian[:, 1, 5] = jacobian[:, 2, 6] = 1.0
    jacobian[:, 0, 7], jacobian[:, 1, 7], jacobian[:, 2, 7] = -c0, -c1, -c2
    jacobian[:, 3, 5], jacobian[:, 3, 6] = -c2, c1
    jacobian[:, 4, 4], jacobian[:, 4, 6] = c2, -c0
    jacobian[:, 5, 4], jacobian[:, 5, 5] = -c1, c0
    line = np.concatenate([directions, np.cross(centres, directions)], axis=1)
    joint = np.zeros((count, 8, 8))
    joint[:, 4:7, 4:7] = np.array([view.direction_covariance for view in views])
    posed = [k for k, view in enumerate(views) if view.pose_covariance is not None]
    if posed:
        pose = np.array([views[k].pose_covariance for k in posed], dtype=np.float64)
        d_direction = -skew(directions[posed])  # d(direction) / d(rotation)
        scale = scales[posed][:, None, None]
        joint[posed, :3, :3] = scale * scale * pose[:, :3, :3]
        cross = scale * pose[:, :3, 3:] @ np.swapaxes(d_direction, 1, 2)
        joint[posed, :3, 4:7] = cross
        joint[posed, 4:7, :3] = np.swapaxes(cross, 1, 2)
        joint[posed, 4:7, 4:7] += d_direction @ pose[:, 3:, 3:] @ np.swapaxes(d_direction, 1, 2)
    covariance = jacobian @ joint @ np.swapaxes(jacobian, 1, 2)
    # spherical normalization (projective.normalized): |L| >= |d| = 1, never zero
    norm = np.linalg.norm(line, axis=1)
    unit = line / norm[:, None]
    jac_unit = (np.eye(6) - unit[:, :, None] * unit[:, None, :]) / norm[:, None, None]
    covariance = jac_unit @ covariance @ np.swapaxes(jac_unit, 1, 2)
    to_direction = jac_unit @ jacobian[:, :, 4:7]
    return [UncertainLine(unit[k], covariance[k], to_direction[k]) for k in range(count)]


def conditioning(first: View, middle: View, last: View) -> tuple[FloatArray, float]:
    """Return the three-ray test's conditioning (module docstring): the origin (the middle
    camera centre) and the scale (1 / the outer baseline; inf for a zero baseline)."""
    baseline = float(np.linalg.norm(last.centre - first.centre))
    return middle.centre, 1.0 / baseline if baseline > 0.0 else math.inf


def three_ray_test(
    first: View,
    middle: View,
    last: View,
    alpha: float,
    point: FloatArray | None = None,
    noise: TrackingNoise | None = None,
    lines: list[UncertainLine] | None = None,
) -> ThreeRayTest:
    """Test whether the rays of three views meet in one point (H0: the feature is static).

    ``alpha`` is the significance level: a static feature is rejected (called moving) with
    probability alpha when the noise model holds. Raises ValueError when the geometry is
    degenerate (coincident centres, parallel outer rays, or Sigma_dd below rank 3).

    With ``point`` (3,), the feature's estimated world position, the test also reports how
    visible motion is in this geometry: a feature moving with velocity v turns ray i by
    (I - d_i d_i') v (t_i - t_middle) / |P - C_i|, which moves d by G v to first order, so
    T's noncentrality is v' G' Sigma_dd^+ G v; ``motion_noncentrality`` are its values over
    unit v along its principal directions (ascending). Some motions are invisible to any three
    rays: an object moving parallel to a camera that moves in a straight line looks static at
    another depth, and motion within the plane of the camera path and the ray only shows at
    third order in the time span.

    With ``noise`` (correlated tracking offsets) the covariance between the three rays is
    added: the views' ``direction_covariance`` must then already hold the offset variance,
    and their ``pixel_jacobian`` be set.

    ``lines``: the three views' ``viewing_line`` at this test's ``conditioning``, if
    computed already (``viewing_lines`` of many tests at once).
    """
    baseline = float(np.linalg.norm(last.centre - first.centre))
    parallax = ray_angle(first.direction, last.direction)
    if not baseline > 0.0:
        raise ValueError('the first and last camera centres coincide (zero baseline)')
    if not parallax > 1e-9:
        raise ValueError('the first and last rays are parallel (zero parallax)')
    origin, scale = middle.centre, 1.0 / baseline
    if lines is None:
        lines = viewing_lines(
            [first, middle, last], np.broadcast_to(origin, (3, 3)), np.full(3, scale)
        )
    distance, jacobians, meet = _concurrency(lines[0].line, lines[1].line, lines[2].line)
    covariance = sum(
        (j @ line.covariance @ j.T for j, line in zip(jacobians, lines, strict=True)),
        start=np.zeros((5, 5)),
    )
    views = (first, middle, last)
    if noise is not None and not noise.white:
        covariance = covariance + _offset_terms(views, lines, jacobians, noise)
    result = relation_test(distance, covariance, THREE_RAY_DOF, alpha)
    world = meet[:3] / meet[3] / scale + origin if abs(meet[3]) > 1e-12 else np.full(3, np.nan)
    sensitivity = None
    if point is not None and np.all(np.isfinite(point)):
        motion = np.zeros((5, 3))
        for view, line, jacobian in zip((first, middle, last), lines, jacobians, strict=True):
            to_point = np.asarray(point, dtype=np.float64) - view.centre
            distance_m = float(np.linalg.norm(to_point))
            if not distance_m > 0.0:
                continue
            turn = (np.eye(3) - np.outer(view.direction, view.direction)) / distance_m
            seconds = (view.stamp_ns - middle.stamp_ns) * 1e-9
            motion += jacobian @ line.direction_jacobian @ turn * seconds
        information = motion.T @ pseudo_inverse_at_rank(covariance, THREE_RAY_DOF) @ motion
        sensitivity = np.maximum(np.linalg.eigvalsh(0.5 * (information + information.T)), 0.0)
    return ThreeRayTest(
        result, (first.frame, middle.frame, last.frame), parallax, baseline, world, sensitivity
    )


def three_ray_relations(
    triples: list[tuple[View, View, View]],
    lines: list[list[UncertainLine] | None],
    alphas: list[float],
    noise: TrackingNoise | None = None,
) -> list[RelationTest | ValueError]:
    """Return ``three_ray_test(first, middle, last, alpha, noise=noise).result`` of many
    triples at once, or the ValueError it raises: the same relation and test on stacked
    arrays (``lines``: each triple's ``viewing_lines`` at its ``conditioning``, None where
    its baseline is zero). Triples the stacked path cannot take (persistent tracker offsets,
    zero baseline or parallax, a degenerate Sigma_dd) go through ``three_ray_test`` itself,
    which gives the result or the error."""
    out: list[RelationTest | ValueError | None] = [None] * len(triples)
    white = noise is None or noise.white
    stacked: list[list[UncertainLine]] = []
    batch: list[int] = []
    for k, (first, _, last) in enumerate(triples):
        triple = lines[k]
        if white and triple is not None and ray_angle(first.direction, last.direction) > 1e-9:
            stacked.append(triple)
            batch.append(k)
    if batch:
        for k, statistic in zip(batch, _stacked_relations(stacked), strict=True):
            if statistic is not None:
                threshold = chi2_quantile(1.0 - alphas[k], THREE_RAY_DOF)
                out[k] = RelationTest(statistic, THREE_RAY_DOF, threshold, statistic > threshold)
    results: list[RelationTest | ValueError] = []
    for k, outcome in enumerate(out):
        if outcome is None:
            try:
                outcome = three_ray_test(*triples[k], alphas[k], noise=noise).result
            except ValueError as error:
                outcome = error
        results.append(outcome)
    return results


def _stacked_relations(lines: list[list[UncertainLine]]) -> list[float | None]:
    """T of ``three_ray_test`` (known lines, independent rays) for K triples of lines at
    once (``_concurrency``, ``relation_test`` stacked); None where the meeting point or
    Sigma_dd is degenerate."""
    count = len(lines)
    l1, l2, l3 = (np.array([triple[k].line for triple in lines]) for k in range(3))
    c1, c2, c3 = (np.array([triple[k].covariance for triple in lines]) for k in range(3))
    d1, d3 = l1[:, :3], l3[:, :3]
    # d_a = L1 . Dual(L3)
    dual1 = np.concatenate([l1[:, 3:], l1[:, :3]], axis=1)
    dual3 = np.concatenate([l3[:, 3:], l3[:, :3]], axis=1)
    coplanar = np.einsum('ki,ki->k', l1, dual3)
    # N = (d1 x d3, 0) and A = N ^ L3
    normal = np.zeros((count, 4))
    normal[:, :3] = np.cross(d1, d3)
    dn_l1 = np.zeros((count, 4, 6))
    dn_l1[:, :3, :3] = -skew(d3)
    dn_l3 = np.zeros((count, 4, 6))
    dn_l3[:, :3, :3] = skew(d1)
    o_l3 = _o_matrices(l3)
    plane = (o_l3 @ normal[:, :, None])[:, :, 0]
    dplane_l1 = o_l3 @ dn_l1
    dplane_l3 = o_l3 @ dn_l3 + _o_bar_matrices(normal)
    # X13 = L1 n A
    gamma = _gamma_matrices(l1)
    meet = (gamma @ plane[:, :, None])[:, :, 0]
    dx_l1 = _gamma_bar_matrices(plane) + gamma @ dplane_l1
    dx_l3 = gamma @ dplane_l3
    norm = np.linalg.norm(meet, axis=1)
    usable = norm > 0.0
    norm = np.where(usable, norm, 1.0)
    unit = meet / norm[:, None]
    dunit = (np.eye(4) - unit[:, :, None] * unit[:, None, :]) / norm[:, None, None]
    dx_l1, dx_l3 = dunit @ dx_l1, dunit @ dx_l3
    # d_b = O(L2) X13
    o_l2 = _o_matrices(l2)
    distance = np.concatenate([coplanar[:, None], (o_l2 @ unit[:, :, None])[:, :, 0]], axis=1)
    jac_l1 = np.concatenate([dual3[:, None, :], o_l2 @ dx_l1], axis=1)
    jac_l2 = np.concatenate([np.zeros((count, 1, 6)), _o_bar_matrices(unit)], axis=1)
    jac_l3 = np.concatenate([dual1[:, None, :], o_l2 @ dx_l3], axis=1)
    covariance = np.zeros((count, 5, 5))
    for jacobian, line_covariance in ((jac_l1, c1), (jac_l2, c2), (jac_l3, c3)):
        covariance += jacobian @ line_covariance @ np.swapaxes(jacobian, 1, 2)
    # T = d' Sigma_dd^+ d at rank 3 (projective.pseudo_inverse_at_rank)
    values, vectors = np.linalg.eigh(0.5 * (covariance + np.swapaxes(covariance, 1, 2)))
    kept = values[:, ::-1][:, :THREE_RAY_DOF]
    basis = vectors[:, :, ::-1][:, :, :THREE_RAY_DOF]
    floor = RANK_TOLERANCE * np.maximum(values.max(axis=1), 0.0)
    usable &= np.all(kept > floor[:, None], axis=1) & (kept[:, 0] > 0)
    projected = np.einsum('kij,ki->kj', basis, distance)
    with np.errstate(divide='ignore', invalid='ignore'):
        statistic = np.sum(projected**2 / kept, axis=1)
    return [float(t) if ok else None for t, ok in zip(statistic, usable, strict=True)]


def _o_matrices(lines: FloatArray) -> FloatArray:
    """``projective.o_matrix`` of lines (K, 6): (K, 4, 4)."""
    out = np.zeros((len(lines), 4, 4))
    l1, l2, l3, l4, l5, l6 = lines.T
    out[:, 0, 1], out[:, 0, 2], out[:, 0, 3] = l3, -l2, -l4
    out[:, 1, 0], out[:, 1, 2], out[:, 1, 3] = -l3, l1, -l5
    out[:, 2, 0], out[:, 2, 1], out[:, 2, 3] = l2, -l1, -l6
    out[:, 3, 0], out[:, 3, 1], out[:, 3, 2] = l4, l5, l6
    return out


def _o_bar_matrices(points: FloatArray) -> FloatArray:
    """``projective.o_bar_matrix`` of points (K, 4): (K, 4, 6)."""
    out = np.zeros((len(points), 4, 6))
    x, y, z, w = points.T
    out[:, 0, 1], out[:, 0, 2], out[:, 0, 3] = -z, y, -w
    out[:, 1, 0], out[:, 1, 2], out[:, 1, 4] = z, -x, -w
    out[:, 2, 0], out[:, 2, 1], out[:, 2, 5] = -y, x, -w
    out[:, 3, 3], out[:, 3, 4], out[:, 3, 5] = x, y, z
    return out


def _gamma_matrices(lines: FloatArray) -> FloatArray:
    """``projective.gamma_matrix`` of lines (K, 6): (K, 4, 4)."""
    out = np.zeros((len(lines), 4, 4))
    out[:, :3, :3] = -skew(lines[:, 3:])
    out[:, :3, 3] = -lines[:, :3]
    out[:, 3, :3] = lines[:, :3]
    return out


def _gamma_bar_matrices(planes: FloatArray) -> FloatArray:
    """``projective.gamma_bar_matrix`` of planes (K, 4): (K, 4, 6)."""
    out = np.zeros((len(planes), 4, 6))
    out[:, 0, 0] = out[:, 1, 1] = out[:, 2, 2] = -planes[:, 3]
    out[:, :3, 3:] = skew(planes[:, :3])
    out[:, 3, :3] = planes[:, :3]
    return out


def _offset_terms(
    views: tuple[View, View, View],
    lines: list[UncertainLine],
    jacobians: list[FloatArray],
    noise: TrackingNoise,
) -> FloatArray:
    """Return the covariance (5, 5) the tracking offsets shared between the three rays add
    to Sigma_dd: sum over pairs i != j of J_i (dL_i/dd_i) Sigma_didj (dL_j/dd_j)' J_j'."""
    missing = [view.frame for view in views if view.pixel_jacobian is None]
    if missing:
        raise ValueError(f'views of frames {missing} carry no pixel Jacobian for the offsets')
    cross = noise.cross_covariances(
        np.array([view.stamp_ns for view in views]),
        np.array([view.pixel_jacobian for view in views]),
    )
    to_distance = [j @ line.direction_jacobian for j, line in zip(jacobians, lines, strict=True)]
    total = np.zeros((5, 5))
    for i in range(3):
        for j in range(3):
            if i != j:
                total += to_distance[i] @ cross[i, j] @ to_distance[j].T
    return total


def _concurrency(
    l1: FloatArray, l2: FloatArray, l3: FloatArray
) -> tuple[FloatArray, list[FloatArray], FloatArray]:
    """Return the distance vector d (5,) of the three-ray relation, its Jacobians (5, 6)
    with respect to the three lines (see the module docstring) and X13 (4,), the point of
    ray 1 nearest to ray 3 (unnormalized)."""
    d1, d3 = l1[:3], l3[:3]
    # d_a: rays 1 and 3 coplanar
    coplanar, da_l1, da_l3 = line_coplanarity(l1, l3)
    # N = (d1 x d3, 0): the common perpendicular's direction
    normal = np.append(_cross(d1, d3), 0.0)
    dn_l1 = np.zeros((4, 6))
    dn_l1[:3, :3] = -skew(d3)
    dn_l3 = np.zeros((4, 6))
    dn_l3[:3, :3] = skew(d1)
    # A = N ^ L3, the plane through ray 3 along the common perpendicular
    plane, da_n, da_line3 = join_point_line(normal, l3)
    dplane_l1 = da_n @ dn_l1
    dplane_l3 = da_n @ dn_l3 + da_line3
    # X13 = L1 n A: ray 1's point nearest to ray 3
    meet, dx_line1, dx_plane = meet_line_plane(l1, plane)
    dx_l1 = dx_line1 + dx_plane @ dplane_l1
    dx_l3 = dx_plane @ dplane_l3
    meet_unit, dunit = normalized(meet)
    dx_l1, dx_l3 = dunit @ dx_l1, dunit @ dx_l3
    # d_b = O(L2) X13: the plane through X13 and ray 2
    o_l2 = o_matrix(l2)
    distance = np.concatenate([[coplanar], o_l2 @ meet_unit])
    jac_l1 = np.vstack([da_l1[None, :], o_l2 @ dx_l1])
    jac_l2 = np.vstack([np.zeros((1, 6)), o_bar_matrix(meet_unit)])
    jac_l3 = np.vstack([da_l3[None, :], o_l2 @ dx_l3])
    return distance, [jac_l1, jac_l2, jac_l3], meet


def pixel_ray_directions(
    rays_camera: FloatArray, ray_jacobians: FloatArray, rotation: FloatArray, pixel_sigma: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Return world unit directions (N, 3), their covariances (N, 3, 3) and their Jacobians
    with respect to the pixel (N, 3, 2) from camera-frame rays r = (x_n, y_n, 1) (N, 3),
    dr/dpixel (N, 3, 2) and R_world_camera (3, 3), for an isotropic pixel noise of
    ``pixel_sigma`` px."""
    norms = np.linalg.norm(rays_camera, axis=1)
    units = rays_camera / norms[:, None]
    # d(r / |r|) / dr = (I - u u') / |r|
    d_unit = (np.eye(3)[None] - units[:, :, None] * units[:, None, :]) / norms[:, None, None]
    jacobian = rotation @ d_unit @ ray_jacobians  # (N, 3, 2)
    covariance = pixel_sigma**2 * jacobian @ np.swapaxes(jacobian, 1, 2)
    return units @ rotation.T, covariance, jacobian
