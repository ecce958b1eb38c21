"""The MonoSLAM filter's models with analytic Jacobians (Davison et al. 2007; Civera et al. 2008).

Camera x_c (13,) = (r m, q = (qw, qx, qy, qz) of R_world_camera, v m/s world, w rad/s camera);
features: inverse depth (6,) or Euclidean (3,). Design notes: docs/design/monoslam_core.md.
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
    """Return the camera (13,), F (13, 13) and Q (13, 13) after ``dt_s`` s of constant velocity."""
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
    """Return the unit ray m (3,) of (theta, phi) rad about R_ref (3, 3), dm/d(angles) (3, 2)."""
    st, ct, sp, cp = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
    local = np.array([cp * st, -sp, cp * ct])
    d_local = np.array([[cp * ct, -sp * st], [0.0, -cp], [-cp * st, -sp * ct]])
    return reference @ local, reference @ d_local


def angles_from_ray(reference: FloatArray, ray: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Return (theta, phi) (2,) rad of a direction (3,) about R_ref and their Jacobian (2, 3)."""
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
    """Return a feature's direction d (3,) from the centre, dd/d(feature) (3, n), dd/dr (3, 3)."""
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
    """``feature_direction``'s directions (M, 3) for many (value, reference or None) points."""
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
    """Return pixel (2,), d/d(camera) (2, 13), d/d(feature) (2, n) and h_c[2] (0: beyond fold)."""
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
    """Return which camera-frame directions (N, 3) in front lie beyond the lens's fold radius."""
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
    """``project_feature`` for M points: pixels (M, 2), (M, 2, 13), per point (2, n), h_c[2]."""
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
    """Return the pixel (2,) of a world point (3,) m, d(pixel)/d(camera) (2, 13) and h_c[2]."""
    pixel, d_camera, _, depth = project_feature(camera_model, camera, point, None)
    return pixel, d_camera, depth


def new_inverse_depth_feature(
    camera_model: CameraModel,
    camera: FloatArray,
    pixel: ArrayLike,
    rho: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Return a feature (6,) at a raw pixel (2,) with ``rho`` (1/m), R_ref (3, 3), dy/d(camera)
    (6, 13) and dy/d(pixel) (6, 2); the caller adds rho's own variance."""
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
    """Return Civera et al.'s linearity index L_d (N,) of inverse-depth features (N, 6)."""
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
