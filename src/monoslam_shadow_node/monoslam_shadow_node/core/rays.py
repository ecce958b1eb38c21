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
from dataclasses import dataclass

import numpy as np

from monoslam_shadow_node.core.projective import (
    FloatArray,
    RelationTest,
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
from monoslam_shadow_node.core.tracking_noise import TrackingNoise
from slam_core.geometry.so3 import skew

THREE_RAY_DOF = 3


@dataclass(frozen=True, eq=False)
class View:
    """One sighting of a feature, everything in the world frame.

    ``centre`` (3,) m is the camera centre, ``direction`` (3,) the unit viewing ray,
    ``direction_covariance`` (3, 3) its covariance from the pixel noise alone (rank 2),
    ``pose_covariance`` (6, 6) the camera pose covariance over (position m, rotation rad about
    the world axes) as in geometry_msgs/PoseWithCovariance, or None for a known pose.
    ``frame`` is the index of the image the feature was seen in. ``pixel_jacobian`` (3, 2)
    is d(direction)/d(pixel), which the correlated tracking offsets need (None: not known,
    the view's errors are taken as independent of every other view's).
    """

    frame: int
    stamp_ns: int
    centre: FloatArray
    direction: FloatArray
    direction_covariance: FloatArray
    pose_covariance: FloatArray | None = None
    pixel_jacobian: FloatArray | None = None


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


def three_ray_test(
    first: View,
    middle: View,
    last: View,
    alpha: float,
    point: FloatArray | None = None,
    noise: TrackingNoise | None = None,
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
    """
    baseline = float(np.linalg.norm(last.centre - first.centre))
    parallax = ray_angle(first.direction, last.direction)
    if not baseline > 0.0:
        raise ValueError('the first and last camera centres coincide (zero baseline)')
    if not parallax > 1e-9:
        raise ValueError('the first and last rays are parallel (zero parallax)')
    origin, scale = middle.centre, 1.0 / baseline
    lines = [viewing_line(view, origin, scale) for view in (first, middle, last)]
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
