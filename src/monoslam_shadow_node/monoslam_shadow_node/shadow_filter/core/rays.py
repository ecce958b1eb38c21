"""Viewing rays as uncertain Pluecker lines, and the three-ray test of paper 001 (III-A).

Design notes: docs/design/shadow_filter_core.md."""

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
    """One sighting of a feature, world frame: ``centre`` (3,) m, unit ``direction`` (3,) with
    its pixel-noise covariance (3, 3), ``pose_covariance`` (6, 6) or None (known pose),
    ``pixel_jacobian`` (3, 2) d(direction)/d(pixel) or None, ``pose_cross`` earlier stamp ->
    (6, 6) cross-covariance or None (independent)."""

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
    """A Pluecker line (6,), its covariance (6, 6) and d(line)/d(direction) (6, 3)."""

    line: FloatArray
    covariance: FloatArray
    direction_jacobian: FloatArray


@dataclass(frozen=True, eq=False)
class ThreeRayTest:
    """One three-ray test: ``point`` (3,) m is ray 1's point nearest ray 3 (NaN: parallel);
    ``motion_noncentrality`` (3,) per (m/s)^2, ascending, or None without a position."""

    result: RelationTest
    frames: tuple[int, int, int]
    parallax_rad: float
    baseline_m: float
    point: FloatArray
    motion_noncentrality: FloatArray | None = None


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """a x b for two 3-vectors, faster than np.cross."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def ray_angle(first: FloatArray, second: FloatArray) -> float:
    """Return the angle (rad) between two unit directions."""
    return math.atan2(float(np.linalg.norm(_cross(first, second))), float(np.dot(first, second)))


def viewing_line(view: View, origin: FloatArray, scale: float) -> UncertainLine:
    """Return the view's ray as an uncertain line in coordinates (x - origin) * scale,
    spherically normalized."""
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
    """Return ``viewing_line`` of N views at once (``origins`` (N, 3), ``scales`` (N,))."""
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
    """Return the test's origin (3,) m and scale (1 / outer baseline, 1/m; inf for zero)."""
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
    """Test whether three views' rays meet in one point (H0: static) at level ``alpha``.

    ``point`` (3,) m: the estimated position, for ``motion_noncentrality``; ``noise``: offsets
    persisting between the rays; ``lines``: the views' lines at ``conditioning``, if known.
    Raises ValueError for coincident centres, parallel outer rays or Sigma_dd below rank 3.
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
    """Return ``three_ray_test(...).result`` of many triples, or the ValueError it raises
    (``lines``: each triple's lines at its ``conditioning``, None for a zero baseline)."""
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
    """T of K triples of lines at once (independent rays); None where degenerate."""
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
    """Return the covariance (5, 5) the offsets shared between the three rays add to d."""
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
    """Return d (5,), its Jacobians (5, 6) by the three lines, and X13 (4,) unnormalized."""
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
    """Return world unit directions (N, 3), covariances (N, 3, 3) and d/dpixel (N, 3, 2) of
    camera rays (x_n, y_n, 1) (N, 3) with dr/dpixel (N, 3, 2), R_world_camera, noise px."""
    norms = np.linalg.norm(rays_camera, axis=1)
    units = rays_camera / norms[:, None]
    # d(r / |r|) / dr = (I - u u') / |r|
    d_unit = (np.eye(3)[None] - units[:, :, None] * units[:, None, :]) / norms[:, None, None]
    jacobian = rotation @ d_unit @ ray_jacobians  # (N, 3, 2)
    covariance = pixel_sigma**2 * jacobian @ np.swapaxes(jacobian, 1, 2)
    return units @ rotation.T, covariance, jacobian
