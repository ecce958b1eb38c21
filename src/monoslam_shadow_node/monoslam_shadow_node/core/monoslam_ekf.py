"""The MonoSLAM EKF steps on a FilterState: constant velocity prediction, the predicted
measurements with their innovation covariances (the active search regions), and the gated
update of all accepted measurements at once in Joseph form.

A measurement i is predicted with S_i = H_i P H_i^T + R, R = pixel_sigma_px^2 I, and rejected
when its Mahalanobis distance exceeds the chi-square gate (``MonoSlamConfig.gate``). The
update is P = (I - K H) P (I - K H)^T + K R K^T, then the quaternion is renormalized (with
its Jacobian).
"""

from __future__ import annotations

import numpy as np

from monoslam_shadow_node.core.monoslam_model import (
    CAMERA_SIZE,
    Q_SLICE,
    FloatArray,
    predict_camera,
    project_feature,
)
from monoslam_shadow_node.core.monoslam_state import FeatureBlock, FilterState
from monoslam_shadow_node.core.monoslam_types import IntArray, MonoSlamConfig
from slam_core.camera import CameraModel


def predict(state: FilterState, dt_s: float, config: MonoSlamConfig) -> None:
    """Constant velocity prediction of the camera over ``dt_s`` s; features are static."""
    sigmas = config.linear_acceleration_sigma, config.angular_acceleration_sigma
    camera, f, q = predict_camera(state.x[:CAMERA_SIZE], dt_s, *sigmas)
    state.x[:CAMERA_SIZE] = camera
    c = slice(0, CAMERA_SIZE)
    state.p[c, c] = f @ state.p[c, c] @ f.T + q
    state.p[c, CAMERA_SIZE:] = f @ state.p[c, CAMERA_SIZE:]
    state.p[CAMERA_SIZE:, c] = state.p[c, CAMERA_SIZE:].T


def predicted_measurements(
    state: FilterState,
    camera_model: CameraModel,
    dt_s: float,
    config: MonoSlamConfig,
    ids: list[int] | None = None,
) -> tuple[IntArray, FloatArray, FloatArray]:
    """Return the features' (those in ``ids``, or all) predicted raw pixels ``dt_s`` s ahead:
    ids (M,), pixels (M, 2) and innovation covariances (M, 2, 2) px^2; the state is unchanged.
    Features behind the camera are left out."""
    sigmas = config.linear_acceleration_sigma, config.angular_acceleration_sigma
    camera, f, q = predict_camera(state.x[:CAMERA_SIZE], dt_s, *sigmas)
    p_cc = f @ state.p[:CAMERA_SIZE, :CAMERA_SIZE] @ f.T + q
    wanted = None if ids is None else set(ids)
    out_ids, out_pixels, out_s = [], [], []
    for feature in state.features:
        if wanted is not None and feature.id not in wanted:
            continue
        block = slice(feature.start, feature.start + feature.size)
        pixel, h_c, h_f, depth = project_feature(
            camera_model, camera, state.x[block], feature.reference
        )
        if depth <= 0.0:
            continue
        p_cf = f @ state.p[:CAMERA_SIZE, block]
        s = h_c @ p_cc @ h_c.T + 2.0 * h_c @ p_cf @ h_f.T + h_f @ state.p[block, block] @ h_f.T
        out_ids.append(feature.id)
        out_pixels.append(pixel)
        out_s.append(s + config.pixel_sigma_px**2 * np.eye(2))
    return (
        np.array(out_ids, dtype=np.int64),
        np.array(out_pixels).reshape(-1, 2),
        np.array(out_s).reshape(-1, 2, 2),
    )


def gated_update(
    state: FilterState,
    camera_model: CameraModel,
    observed: dict[int, FloatArray],
    known: list[tuple[FloatArray, FloatArray]],
    config: MonoSlamConfig,
) -> tuple[list[int], list[int], int]:
    """Gate and apply all measurements of the state's features (``observed``: track id ->
    raw pixel (2,)) and of known points (``known``: world point (3,) m, raw pixel (2,)),
    counting each feature's attempt; return the measured and rejected feature ids and the
    number of known points used."""
    n = len(state.x)
    camera = state.x[:CAMERA_SIZE]
    rows: list[FloatArray] = []
    residuals: list[FloatArray] = []
    measured: list[int] = []
    rejected: list[int] = []
    sigma2 = config.pixel_sigma_px**2
    gate = config.gate
    c = slice(0, CAMERA_SIZE)
    # (pixel, known point or None, feature or None): known points first, then features
    candidates: list[tuple[FloatArray, FloatArray | None, FeatureBlock | None]] = [
        (pixel, point, None) for point, pixel in known
    ]
    candidates += [(observed[f.id], None, f) for f in state.features if f.id in observed]
    known_used = 0
    for pixel, point, feature in candidates:
        block: slice | None = None
        if feature is None and point is not None:
            predicted, h_c, h_f, depth = project_feature(camera_model, camera, point, None)
        elif feature is not None:
            block = slice(feature.start, feature.start + feature.size)
            predicted, h_c, h_f, depth = project_feature(
                camera_model, camera, state.x[block], feature.reference
            )
        ok = depth > 0.0
        if ok:
            s = h_c @ state.p[c, c] @ h_c.T + sigma2 * np.eye(2)
            if block is not None:
                cross = h_c @ state.p[c, block] @ h_f.T
                s += cross + cross.T + h_f @ state.p[block, block] @ h_f.T
            innovation = pixel - predicted
            ok = float(innovation @ np.linalg.solve(s, innovation)) <= gate
        if feature is not None:
            feature.attempts += 1
            (measured if ok else rejected).append(feature.id)
            feature.successes += int(ok)
            feature.consecutive_failures = 0 if ok else feature.consecutive_failures + 1
        if not ok:
            continue
        known_used += int(feature is None)
        row = np.zeros((2, n))
        row[:, c] = h_c
        if block is not None:
            row[:, block] = h_f
        rows.append(row)
        residuals.append(pixel - predicted)
    if rows:
        joseph_update(state, np.vstack(rows), np.concatenate(residuals), sigma2)
    return measured, rejected, known_used


def joseph_update(state: FilterState, h: FloatArray, residual: FloatArray, sigma2: float) -> None:
    """x += K nu; P = (I - K H) P (I - K H)^T + K R K^T, R = sigma2 I; renormalize q."""
    ph_t = state.p @ h.T
    s = h @ ph_t + sigma2 * np.eye(len(h))
    gain = np.linalg.solve(s, ph_t.T).T
    state.x = state.x + gain @ residual
    a = np.eye(len(state.x)) - gain @ h
    p = a @ state.p @ a.T + sigma2 * (gain @ gain.T)
    norm = float(np.linalg.norm(state.x[Q_SLICE]))
    q = state.x[Q_SLICE] / norm
    jacobian = (np.eye(4) - np.outer(q, q)) / norm
    state.x[Q_SLICE] = q
    p[Q_SLICE, :] = jacobian @ p[Q_SLICE, :]
    p[:, Q_SLICE] = p[:, Q_SLICE] @ jacobian.T
    state.p = 0.5 * (p + p.T)
