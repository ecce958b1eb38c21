"""The models of the MonoSLAM filter with their analytic Jacobians (Davison et al. 2007;
Civera, Davison and Montiel 2008).

Camera state x_c (13,) = (r, q, v, w):

- r (3,) m: the optical centre in the world (``map``) frame;
- q (4,) = (qw, qx, qy, qz): the unit quaternion of R_world_camera (the optical frame: x
  right, y down, z forward). ``slam_core.geometry.quaternion.rotation_from_quaternion`` is
  the quadratic form of q, exactly a rotation for |q| = 1; the filter renormalizes after
  every update;
- v (3,) m/s: linear velocity in the world frame; w (3,) rad/s: angular velocity in the camera
  frame.

Constant velocity model over dt (``predict_camera``): unknown linear and angular
accelerations a, alpha of spectral densities ``sigma_a^2`` (m^2/s^3) and ``sigma_alpha^2``
(rad^2/s^3) give velocity impulses V = a dt, Omega = alpha dt with covariance diag(sigma_a^2
dt, sigma_alpha^2 dt) and

    r' = r + (v + V) dt,   q' = q (x) exp((w + Omega) dt),   v' = v + V,   w' = w + Omega,

F = dx'/dx and G = dx'/d(V, Omega), Q = G diag(.) G^T.

Point features, two parametrizations:

- inverse depth (Civera et al.), y (6,) = (x0, y0, z0, theta, phi, rho): the point is
  p = p0 + m(theta, phi) / rho, p0 the optical centre when the feature was first seen,
  m = R_ref (cos phi sin theta, -sin phi, cos phi cos theta) a unit ray and rho > 0 the inverse
  depth along it (1/m). R_ref is a constant per feature: the camera's orientation estimate
  when the feature was added, so the angles are small and far from the parametrization's
  singularity (phi = +-90 deg) for any ray the camera could see. The measurement is linear in
  y near infinite depth (rho -> 0), which makes undelayed initialization possible;
- Euclidean, y (3,) = p. A feature moves to it once its linearity index (``linearity_indices``,
  Civera et al. eq. 16) says the Euclidean measurement model is close to linear over its depth
  uncertainty: 3 states instead of 6.

Why inverse depth and not the inverse scaling of paper 001's reference [11] (Marzorati et
al., a homogeneous point (x, y, z, w) with w = 1/s): both give measurement equations that are
nearly linear for distant and newly seen points, and [11] reports the same accuracy; inverse
depth has an established test for when a point may be converted to 3 Euclidean states, and
its anchor ties each feature to the camera that first saw it, which keeps the covariance of a
newly added feature exactly the first-order propagation of that camera's and that ray's
uncertainty. The Shadow filter keeps the homogeneous form (its per-feature EKF needs w = 0 for
points at infinity); the two meet only in the handover, a Euclidean point with covariance.

Measurement (``project_feature``): h_c = R^T (rho (p0 - r) + m) for inverse depth, R^T (p - r)
for Euclidean (a direction in the camera frame; scaling by rho > 0 does not change the pixel),
then the lens model of ``CameraModel`` (pinhole + plumb_bob / rational distortion). A
direction beyond the lens's fold radius (``CameraModel.fold_radius``: far off the axis, where
the distortion polynomial bends back and would map it into the image, for example a point
beside the camera) is not visible, like one behind it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import (
    exp_quaternion,
    left_matrix,
    quaternion_product,
    right_matrix,
    rotate_jacobian,
    rotate_transposed_jacobian,
    rotation_from_quaternion,
)

CAMERA_SIZE = 13
INVERSE_DEPTH_SIZE = 6
EUCLIDEAN_SIZE = 3
R_SLICE, Q_SLICE, V_SLICE, W_SLICE = slice(0, 3), slice(3, 7), slice(7, 10), slice(10, 13)


# --- motion model ------------------------------------------------------------------------------


def predict_camera(
    camera: ArrayLike, dt_s: float, sigma_a: float, sigma_alpha: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Return the predicted camera state (13,), F = dx'/dx (13, 13) and Q (13, 13) after dt_s
    seconds of the constant velocity model (module docstring)."""
    x = np.asarray(camera, dtype=np.float64)
    r, q, v, w = x[R_SLICE], x[Q_SLICE], x[V_SLICE], x[W_SLICE]
    dq, d_dq = exp_quaternion(w * dt_s)
    out = np.concatenate([r + v * dt_s, quaternion_product(q, dq), v, w])
    f = np.eye(CAMERA_SIZE)
    f[R_SLICE, V_SLICE] = dt_s * np.eye(3)
    f[Q_SLICE, Q_SLICE] = right_matrix(dq)
    dq_dw = left_matrix(q) @ d_dq * dt_s  # (4, 3)
    f[Q_SLICE, W_SLICE] = dq_dw
    g = np.zeros((CAMERA_SIZE, 6))
    g[R_SLICE, :3] = dt_s * np.eye(3)
    g[Q_SLICE, 3:] = dq_dw
    g[V_SLICE, :3] = np.eye(3)
    g[W_SLICE, 3:] = np.eye(3)
    impulses = np.concatenate([np.full(3, sigma_a**2 * dt_s), np.full(3, sigma_alpha**2 * dt_s)])
    return out, f, (g * impulses) @ g.T


# --- features ------------------------------------------------------------------------------------


def ray_from_angles(
    reference: FloatArray, theta: float, phi: float
) -> tuple[FloatArray, FloatArray]:
    """Return the unit ray m (3,) in the world of angles (theta, phi) rad about R_ref (3, 3)
    and dm/d(theta, phi) (3, 2)."""
    st, ct, sp, cp = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
    local = np.array([cp * st, -sp, cp * ct])
    d_local = np.array([[cp * ct, -sp * st], [0.0, -cp], [-cp * st, -sp * ct]])
    return reference @ local, reference @ d_local


def angles_from_ray(reference: FloatArray, ray: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Return (theta, phi) (2,) rad of a world direction (3,) (any length) about R_ref and
    their Jacobian (2, 3) with respect to the direction."""
    d = np.asarray(reference, dtype=np.float64).T @ np.asarray(ray, dtype=np.float64)
    x, y, z = d
    horizontal2 = x * x + z * z
    horizontal = np.sqrt(horizontal2)
    norm2 = horizontal2 + y * y
    angles = np.array([np.arctan2(x, z), np.arctan2(-y, horizontal)])
    d_local = np.array(
        [
            [z / horizontal2, 0.0, -x / horizontal2],
            [x * y / (norm2 * horizontal), -horizontal / norm2, z * y / (norm2 * horizontal)],
        ]
    )
    return angles, d_local @ np.asarray(reference, dtype=np.float64).T


def feature_direction(
    kind_size: int, feature: FloatArray, reference: FloatArray | None, centre: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Return a feature's world direction d (3,) from the optical centre (any positive scale),
    dd/d(feature) (3, n) and dd/dr (3, 3), for a Euclidean (n = 3) or inverse-depth (n = 6)
    feature."""
    if kind_size == EUCLIDEAN_SIZE:
        return feature - centre, np.eye(3), -np.eye(3)
    if reference is None:
        raise ValueError('an inverse-depth feature needs its reference rotation')
    anchor, theta, phi, rho = feature[:3], feature[3], feature[4], feature[5]
    ray, d_ray = ray_from_angles(reference, float(theta), float(phi))
    direction = rho * (anchor - centre) + ray
    jacobian = np.empty((3, INVERSE_DEPTH_SIZE))
    jacobian[:, :3] = rho * np.eye(3)
    jacobian[:, 3:5] = d_ray
    jacobian[:, 5] = anchor - centre
    return direction, jacobian, -rho * np.eye(3)


def feature_directions(
    features: list[tuple[FloatArray, FloatArray | None]], centre: FloatArray
) -> FloatArray:
    """``feature_direction`` (the direction alone) for many points at once: (value (3,) or
    (6,), reference or None) per point, a Euclidean (or known) point or an inverse-depth
    feature; returns (M, 3), the same numbers as one by one."""
    directions = np.empty((len(features), 3))
    inverse = [k for k, (value, _) in enumerate(features) if len(value) == INVERSE_DEPTH_SIZE]
    euclidean = [k for k, (value, _) in enumerate(features) if len(value) == EUCLIDEAN_SIZE]
    if len(inverse) + len(euclidean) != len(features):
        raise ValueError('a point is 3 (Euclidean) or 6 (inverse depth) values')
    if euclidean:
        directions[euclidean] = np.array([features[k][0] for k in euclidean]) - centre
    if inverse:
        values = np.array([features[k][0] for k in inverse])
        references = [features[k][1] for k in inverse]
        if any(reference is None for reference in references):
            raise ValueError('an inverse-depth feature needs its reference rotation')
        theta, phi = values[:, 3], values[:, 4]
        st, ct, sp, cp = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
        local = np.stack([cp * st, -sp, cp * ct], axis=1)
        rays = (np.array(references) @ local[:, :, None])[:, :, 0]
        directions[inverse] = values[:, 5, None] * (values[:, :3] - centre) + rays
    return directions


def project_feature(
    camera_model: CameraModel,
    camera: FloatArray,
    feature: FloatArray,
    reference: FloatArray | None,
) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """Return the predicted raw pixel (2,) of a feature, d(pixel)/d(camera state) (2, 13),
    d(pixel)/d(feature) (2, n) and the visibility check value: h_c[2] (> 0: in front), 0 for a
    direction beyond the lens's fold (module docstring; NaN pixel and zero Jacobians then)."""
    r, q = camera[R_SLICE], camera[Q_SLICE]
    direction, d_feature, d_centre = feature_direction(len(feature), feature, reference, r)
    rot_t = rotation_from_quaternion(q).T
    h_c = rot_t @ direction
    if h_c[2] > 0.0 and beyond_fold(camera_model, h_c[None])[0]:
        h_c[2] = 0.0
    if h_c[2] <= 0.0:
        return np.full(2, np.nan), np.zeros((2, CAMERA_SIZE)), np.zeros((2, len(feature))), h_c[2]
    pixel, d_pixel = camera_model.project_with_jacobian(h_c[None])
    d_pixel_hc = d_pixel[0]
    d_camera = np.zeros((2, CAMERA_SIZE))
    d_camera[:, R_SLICE] = d_pixel_hc @ rot_t @ d_centre
    d_camera[:, Q_SLICE] = d_pixel_hc @ rotate_transposed_jacobian(q, direction)
    return pixel[0], d_camera, d_pixel_hc @ rot_t @ d_feature, float(h_c[2])


def beyond_fold(camera_model: CameraModel, h_c: FloatArray) -> NDArray[np.bool_]:
    """Return which camera-frame directions (N, 3) in front of the camera lie beyond the lens's
    fold radius (module docstring); False for the others."""
    with np.errstate(divide='ignore', invalid='ignore'):
        radius = np.hypot(h_c[:, 0], h_c[:, 1]) / h_c[:, 2]
    return np.asarray((h_c[:, 2] > 0.0) & (radius >= camera_model.fold_radius()))


def project_features(
    camera_model: CameraModel,
    camera: FloatArray,
    features: list[tuple[FloatArray, FloatArray | None]],
    *,
    jacobians: bool = True,
) -> tuple[FloatArray, FloatArray, list[FloatArray], FloatArray]:
    """``project_feature`` for many points at once: (value (3,) or (6,), reference or None)
    per point (a known point, a Euclidean or an inverse-depth feature). Returns the pixels
    (M, 2), d(pixel)/d(camera state) (M, 2, 13), d(pixel)/d(feature) per point (2, n) and the
    depth check values h_c[2] (M,); points behind the camera get NaN pixels and zero
    Jacobians, as there; so do points beyond the lens's fold, with check value 0. Without
    ``jacobians`` the Jacobians are all zero (only the pixels are wanted)."""
    count = len(features)
    r, q = camera[R_SLICE], camera[Q_SLICE]
    rot_t = rotation_from_quaternion(q).T
    directions = np.empty((count, 3))
    d_centre = np.empty((count, 3, 3))
    inverse = [k for k, (value, _) in enumerate(features) if len(value) == INVERSE_DEPTH_SIZE]
    euclidean = [k for k, (value, _) in enumerate(features) if len(value) == EUCLIDEAN_SIZE]
    if len(inverse) + len(euclidean) != count:
        raise ValueError('a point is 3 (Euclidean) or 6 (inverse depth) values')
    if euclidean:
        points = np.array([features[k][0] for k in euclidean])
        directions[euclidean] = points - r
        d_centre[euclidean] = -np.eye(3)
    inverse_jacobians = np.empty((len(inverse), 3, INVERSE_DEPTH_SIZE))
    if inverse:
        values = np.array([features[k][0] for k in inverse])
        references = []
        for k in inverse:
            reference = features[k][1]
            if reference is None:
                raise ValueError('an inverse-depth feature needs its reference rotation')
            references.append(reference)
        reference_array = np.array(references)
        theta, phi, rho = values[:, 3], values[:, 4], values[:, 5]
        st, ct, sp, cp = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
        local = np.stack([cp * st, -sp, cp * ct], axis=1)
        rays = np.einsum('nij,nj->ni', reference_array, local)
        offset = values[:, :3] - r
        directions[inverse] = rho[:, None] * offset + rays
        if jacobians:
            d_local = np.zeros((len(inverse), 3, 2))
            d_local[:, 0] = np.stack([cp * ct, -sp * st], axis=1)
            d_local[:, 1, 1] = -cp
            d_local[:, 2] = np.stack([-cp * st, -sp * ct], axis=1)
            inverse_jacobians[:, :, :3] = rho[:, None, None] * np.eye(3)
            inverse_jacobians[:, :, 3:5] = reference_array @ d_local
            inverse_jacobians[:, :, 5] = offset
            d_centre[inverse] = -rho[:, None, None] * np.eye(3)
    h_c = directions @ rot_t.T
    depth = h_c[:, 2].copy()
    depth[(depth > 0.0) & beyond_fold(camera_model, h_c)] = 0.0
    pixels = np.full((count, 2), np.nan)
    d_camera = np.zeros((count, 2, CAMERA_SIZE))
    out_feature = [np.zeros((2, len(value))) for value, _ in features]
    front = np.flatnonzero(depth > 0.0)
    if not len(front):
        return pixels, d_camera, out_feature, depth
    if not jacobians:
        pixels[front] = camera_model.project(h_c[front])
        return pixels, d_camera, out_feature, depth
    projected, d_pixel = camera_model.project_with_jacobian(h_c[front])
    pixels[front] = projected
    d_hc = d_pixel @ rot_t  # (F, 2, 3): d(pixel)/d(direction)
    d_camera[front, :, R_SLICE] = d_hc @ d_centre[front]
    d_camera[front, :, Q_SLICE] = d_pixel @ _rotate_transposed_jacobians(q, directions[front])
    row_of = np.full(count, -1)
    row_of[inverse] = np.arange(len(inverse))
    in_front = row_of[front] >= 0
    products = d_hc[in_front] @ inverse_jacobians[row_of[front[in_front]]]
    for k, product in zip(front[in_front].tolist(), products, strict=True):
        out_feature[k] = product
    products = d_hc[~in_front] @ np.eye(3)
    for k, product in zip(front[~in_front].tolist(), products, strict=True):
        out_feature[k] = product
    return pixels, d_camera, out_feature, depth


def _rotate_transposed_jacobians(q: FloatArray, vectors: FloatArray) -> FloatArray:
    """``rotate_transposed_jacobian`` for many vectors (N, 3): (N, 3, 4)."""
    w, u = float(q[0]), np.asarray(q[1:], dtype=np.float64)
    out = np.empty((len(vectors), 3, 4))
    out[:, :, 0] = 2.0 * w * vectors - 2.0 * np.cross(u, vectors)
    block = (
        -2.0 * vectors[:, :, None] * u[None, None, :]
        + 2.0 * u[None, :, None] * vectors[:, None, :]
    )
    block += 2.0 * (vectors @ u)[:, None, None] * np.eye(3)
    skews = np.zeros((len(vectors), 3, 3))
    skews[:, 0, 1], skews[:, 0, 2] = -vectors[:, 2], vectors[:, 1]
    skews[:, 1, 0], skews[:, 1, 2] = vectors[:, 2], -vectors[:, 0]
    skews[:, 2, 0], skews[:, 2, 1] = -vectors[:, 1], vectors[:, 0]
    out[:, :, 1:] = block + 2.0 * w * skews
    return out


def project_known_point(
    camera_model: CameraModel, camera: FloatArray, point: FloatArray
) -> tuple[FloatArray, FloatArray, float]:
    """Return the raw pixel (2,) of a point of known world position (3,) m, d(pixel)/d(camera
    state) (2, 13) and h_c[2]."""
    pixel, d_camera, _, depth = project_feature(camera_model, camera, point, None)
    return pixel, d_camera, depth


def new_inverse_depth_feature(
    camera_model: CameraModel,
    camera: FloatArray,
    pixel: ArrayLike,
    rho: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Return a new inverse-depth feature (6,) seen at a raw pixel (2,) with inverse depth rho
    (1/m), its reference rotation R_ref (3, 3), dy/d(camera state) (6, 13) and dy/d(pixel)
    (6, 2). The caller adds rho's own variance on the last entry."""
    r, q = camera[R_SLICE], camera[Q_SLICE]
    normalized = camera_model.undistort_points(np.asarray(pixel, dtype=np.float64)[None],
                                               normalized=True)[0]  # fmt: skip
    h_c = np.array([normalized[0], normalized[1], 1.0])
    _, d_lens = camera_model.project_with_jacobian(h_c[None])
    d_hc_pixel = np.zeros((3, 2))
    d_hc_pixel[:2, :] = np.linalg.inv(d_lens[0][:, :2])
    reference = rotation_from_quaternion(q / np.linalg.norm(q))
    world_ray = rotation_from_quaternion(q) @ h_c
    angles, d_angles = angles_from_ray(reference, world_ray)
    feature = np.concatenate([r, angles, [rho]])
    d_camera = np.zeros((INVERSE_DEPTH_SIZE, CAMERA_SIZE))
    d_camera[:3, R_SLICE] = np.eye(3)
    d_camera[3:5, Q_SLICE] = d_angles @ rotate_jacobian(q, h_c)
    d_pixel = np.zeros((INVERSE_DEPTH_SIZE, 2))
    d_pixel[3:5] = d_angles @ rotation_from_quaternion(q) @ d_hc_pixel
    return feature, reference, d_camera, d_pixel


def euclidean_point(feature: FloatArray, reference: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return the Euclidean point (3,) m of an inverse-depth feature (6,) and dp/dy (3, 6)."""
    ray, d_ray = ray_from_angles(reference, float(feature[3]), float(feature[4]))
    rho = float(feature[5])
    jacobian = np.empty((3, INVERSE_DEPTH_SIZE))
    jacobian[:, :3] = np.eye(3)
    jacobian[:, 3:5] = d_ray / rho
    jacobian[:, 5] = -ray / rho**2
    return feature[:3] + ray / rho, jacobian


def linearity_indices(
    features: FloatArray, references: FloatArray, rho_variances: FloatArray, centre: FloatArray
) -> FloatArray:
    """Return Civera et al.'s linearity index L_d (N,) of inverse-depth features (N, 6) with
    their reference rotations (N, 3, 3) and rho variances (N,), seen from the optical centre
    (3,): 4 sigma_d / d_1 |cos alpha|, sigma_d = sigma_rho / rho^2 the depth uncertainty, d_1
    the distance from the centre, alpha the angle between the feature's ray and the current
    one (inf for rho <= 0 or a zero distance). Below ~0.1 the Euclidean model is linear
    enough to switch."""
    features = np.asarray(features, dtype=np.float64).reshape(-1, INVERSE_DEPTH_SIZE)
    theta, phi, rho = features[:, 3], features[:, 4], features[:, 5]
    st, ct, sp, cp = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
    local = np.stack([cp * st, -sp, cp * ct], axis=1)
    rays = (np.asarray(references) @ local[:, :, None])[:, :, 0]
    out = np.full(len(features), np.inf)
    usable = rho > 0.0
    if not np.any(usable):
        return out
    rays, rho, features = rays[usable], rho[usable], features[usable]
    sight = features[:, :3] + rays / rho[:, None] - centre
    distance = np.sqrt((sight[:, None, :] @ sight[:, :, None])[:, 0, 0])
    sigma_depth = np.sqrt(np.maximum(np.asarray(rho_variances)[usable], 0.0)) / rho**2
    with np.errstate(divide='ignore', invalid='ignore'):
        cos_alpha = (rays[:, None, :] @ sight[:, :, None])[:, 0, 0] / distance
        index = 4.0 * sigma_depth / distance * np.abs(cos_alpha)
    out[usable] = np.where(distance > 0.0, index, np.inf)
    return out
