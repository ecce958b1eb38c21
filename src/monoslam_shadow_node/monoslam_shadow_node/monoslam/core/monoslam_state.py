"""The MonoSLAM state: the camera then one block per map feature in x and P, and its edits.

x (n,) = [camera (13): r, q, v, w | feature blocks (6 or 3, + 2 offset states)], P (n, n).
Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_model import (
    CAMERA_SIZE,
    EUCLIDEAN_SIZE,
    INVERSE_DEPTH_SIZE,
    Q_SLICE,
    R_SLICE,
    V_SLICE,
    W_SLICE,
    euclidean_point,
    linearity_indices,
    new_inverse_depth_feature,
    ray_from_angles,
)
from monoslam_shadow_node.monoslam.core.monoslam_types import MapPoint
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import world_angle_jacobian

FAR_M = 1000.0
"""Where along its ray an inverse-depth feature with rho <= 0 is reported (m)."""


POSE_HISTORY = (20, 5, 300)
"""Which earlier pose estimates the filter carries the errors' covariance with
(``monoslam_ekf.pose_cross``), in images back from the current one: every one of the
latest 20, then every 5th image up to 300 back (10 s at 30 Hz). Any two of them are covered
by the later one's table, so the Shadow filter can test a feature over those of its views
(``pose_links``). Dropping the older ones altogether made the errors of views further apart
count as independent, and a covariance cut off so is not one: on the simulator it called 96
of 254 static points DYNAMIC under a drift that, declared in full, gave 1. About 76 poses, 6
columns each in every update (docs/design/shadow_filter.md)."""


def keeps_pose(current: int, earlier: int) -> bool:
    """Whether image ``earlier``'s estimate stays remembered at image ``current``."""
    recent, stride, span = POSE_HISTORY
    back = current - earlier
    return back < recent or (back < span and earlier % stride == 0)


@dataclass
class FeatureBlock:
    """A feature in the state: its track id, block in x, origin, record, probation and offset."""

    id: int
    start: int
    size: int
    reference: FloatArray | None
    source: str
    added_frame: int
    last_seen_frame: int
    attempts: int = 0
    successes: int = 0
    consecutive_failures: int = 0
    probation: bool = False
    cleared: bool = True
    offset_size: int = 0
    first_ray: FloatArray | None = None  # world unit ray it was first seen along
    searches: int = 0  # frames it was predicted in view (with features in the frame)
    found: int = 0  # of those, frames it was observed

    @property
    def extent(self) -> int:
        """The states the feature takes: its point and its offset."""
        return self.size + self.offset_size

    @property
    def offset(self) -> slice | None:
        """Its offset's states in x (None without one)."""
        if not self.offset_size:
            return None
        return slice(self.start + self.size, self.start + self.extent)


class FilterState:
    """The EKF's ``x`` (n,) and ``p`` (n, n) with the ``features`` laid out in it."""

    def __init__(self) -> None:
        self.x = np.zeros(0)
        self.p = np.zeros((0, 0))
        self.features: list[FeatureBlock] = []
        # Cov(error of x, pose error of each remembered earlier estimate) (n, 6 K), over
        # (position, rotation about the world axes) per pose, oldest first, and their
        # stamps and images (remember_pose): kept through every change of x and P
        self.history = np.zeros((0, 0))
        self.history_stamps: list[int] = []
        self.history_frames: list[int] = []

    def start(
        self,
        pose_state: FloatArray,
        pose_covariance: FloatArray,
        velocity_sigma_m_s: float,
        angular_velocity_sigma_rad_s: float,
    ) -> None:
        """Set the camera: pose (7,) (r, q), covariance (7, 7), zero velocities of given sigmas."""
        n = len(self.x) if self.features else CAMERA_SIZE
        x, p = np.zeros(n), np.zeros((n, n))
        x[CAMERA_SIZE:] = self.x[CAMERA_SIZE:n]
        p[CAMERA_SIZE:, CAMERA_SIZE:] = self.p[CAMERA_SIZE:n, CAMERA_SIZE:n]
        x[:7] = pose_state
        p[:7, :7] = pose_covariance
        p[V_SLICE, V_SLICE] = velocity_sigma_m_s**2 * np.eye(3)
        p[W_SLICE, W_SLICE] = angular_velocity_sigma_rad_s**2 * np.eye(3)
        self.x, self.p = x, p
        self.history, self.history_stamps, self.history_frames = np.zeros((n, 0)), [], []

    def insert_inverse_depth(
        self,
        camera_model: CameraModel,
        feature_id: int,
        pixel: FloatArray,
        rho: float,
        rho_variance: float,
        pixel_sigma_px: float,
        source: str,
        frame: int,
        offset_sigma_px: float = 0.0,
    ) -> bool:
        """Append an inverse-depth feature at ``pixel`` with ``rho`` (1/m); True if it went in."""
        feature, reference, d_camera, d_pixel = new_inverse_depth_feature(
            camera_model, self.x[:CAMERA_SIZE], pixel, rho
        )
        if not np.all(np.isfinite(feature)):
            return False
        history = self._history_rows()
        n = len(self.x)
        c = slice(0, CAMERA_SIZE)
        cross = d_camera @ self.p[c, :]  # (6, n)
        block = d_camera @ self.p[c, c] @ d_camera.T
        block += pixel_sigma_px**2 * (d_pixel @ d_pixel.T)
        block += offset_sigma_px**2 * (d_pixel @ d_pixel.T)
        block[5, 5] += rho_variance
        offset_size = 2 if offset_sigma_px > 0.0 else 0
        if offset_size:
            offset_cross = -(offset_sigma_px**2) * d_pixel  # (6, 2)
            cross = np.vstack([cross, np.zeros((2, n))])
            block = np.block(
                [[block, offset_cross], [offset_cross.T, offset_sigma_px**2 * np.eye(2)]]
            )
            feature = np.concatenate([feature, np.zeros(2)])
        size = INVERSE_DEPTH_SIZE + offset_size
        p = np.zeros((n + size, n + size))
        p[:n, :n] = self.p
        p[n:, :n] = cross
        p[:n, n:] = cross.T
        p[n:, n:] = block
        self.p = p
        self.x = np.concatenate([self.x, feature])
        added = np.zeros((size, history.shape[1]))
        added[:INVERSE_DEPTH_SIZE] = d_camera @ history[c]  # the pixel's noise is new
        self.history = np.vstack([history, added])
        first_ray, _ = ray_from_angles(reference, float(feature[3]), float(feature[4]))
        self.features.append(
            FeatureBlock(feature_id, n, INVERSE_DEPTH_SIZE, reference, source, frame, frame,
                         offset_size=offset_size, first_ray=first_ray)
        )  # fmt: skip
        return True

    def to_euclidean(self, feature: FeatureBlock) -> None:
        """Replace an inverse-depth feature's 6 states by its 3 Euclidean ones."""
        assert feature.reference is not None
        start = feature.start
        block = slice(start, start + INVERSE_DEPTH_SIZE)
        point, jacobian = euclidean_point(self.x[block], feature.reference)
        history = self._history_rows()
        # P' = T P T^T with T the identity but for the feature's rows (J over its 6 columns),
        # by blocks: O(n^2), not the O(n^3) of the dense product
        n = len(self.x)
        end = start + INVERSE_DEPTH_SIZE
        rest = np.r_[0:start, end:n]
        crossed = jacobian @ self.p[block, rest]  # (3, n - 6)
        p = np.empty((n - 3, n - 3))
        others = np.r_[0:start, start + 3 : n - 3]
        old, new = self.p, start + 3  # the others' blocks, by slices
        p[:start, :start], p[:start, new:] = old[:start, :start], old[:start, end:]
        p[new:, :start], p[new:, new:] = old[end:, :start], old[end:, end:]
        p[start : start + 3, others] = crossed
        p[others, start : start + 3] = crossed.T
        p[start : start + 3, start : start + 3] = jacobian @ self.p[block, block] @ jacobian.T
        self.x = np.concatenate([self.x[:start], point, self.x[end:]])
        self.p = 0.5 * (p + p.T)
        self.history = np.vstack([history[:start], jacobian @ history[block], history[end:]])
        feature.size, feature.reference = EUCLIDEAN_SIZE, None
        for other in self.features:
            if other.start > start:
                other.start -= 3

    def convert_linear(self, threshold: float) -> list[FeatureBlock]:
        """Convert the inverse-depth features below the linearity ``threshold``; return them."""
        inverse = [
            f for f in self.features if f.size == INVERSE_DEPTH_SIZE and f.reference is not None
        ]
        if not inverse:
            return []
        starts = np.array([feature.start for feature in inverse])
        indices = linearity_indices(
            self.x[starts[:, None] + np.arange(INVERSE_DEPTH_SIZE)],
            np.array([feature.reference for feature in inverse]),
            self.p[starts + 5, starts + 5],
            self.x[R_SLICE],
        )
        converted = []
        for feature, index in zip(inverse, indices.tolist(), strict=True):
            if index < threshold and self.x[feature.start + 5] > 0.0:
                self.to_euclidean(feature)
                converted.append(feature)
        return converted

    def reset_offset(self, feature: FeatureBlock, sigma_px: float) -> None:
        """Forget a feature's tracker offset: 0, sigma ``sigma_px``, uncorrelated with the rest."""
        offset = feature.offset
        if offset is None:
            return
        self.x[offset] = 0.0
        self.p[offset, :] = 0.0
        self.p[:, offset] = 0.0
        self.p[offset, offset] = sigma_px**2 * np.eye(2)
        self._history_rows()[offset] = 0.0

    def add_offset(self, feature: FeatureBlock, sigma_px: float) -> None:
        """Give a feature a tracker offset: 2 states, 0 with sigma ``sigma_px``, uncorrelated."""
        if feature.offset_size:
            return
        at, n = feature.start + feature.size, len(self.x)
        history = self._history_rows()
        p = np.zeros((n + 2, n + 2))
        p[:at, :at], p[:at, at + 2 :] = self.p[:at, :at], self.p[:at, at:]
        p[at + 2 :, :at], p[at + 2 :, at + 2 :] = self.p[at:, :at], self.p[at:, at:]
        p[at : at + 2, at : at + 2] = sigma_px**2 * np.eye(2)
        self.p = p
        self.x = np.concatenate([self.x[:at], np.zeros(2), self.x[at:]])
        self.history = np.vstack([history[:at], np.zeros((2, history.shape[1])), history[at:]])
        for other in self.features:
            if other.start > feature.start:
                other.start += 2
        feature.offset_size = 2

    def remove(self, feature: FeatureBlock) -> None:
        """Take a feature out of the state."""
        start, end = feature.start, feature.start + feature.extent
        self.history = np.delete(self._history_rows(), np.s_[start:end], axis=0)
        self.x = np.concatenate([self.x[:start], self.x[end:]])
        self.p = _without_block(self.p, start, end)
        self.features.remove(feature)
        for other in self.features:
            if other.start > feature.start:
                other.start -= feature.extent

    def map_point(self, feature: FeatureBlock, active: bool) -> MapPoint:
        """Return the feature as a world point (MapPoint; ``active``: still in the filter)."""
        block = slice(feature.start, feature.start + feature.size)
        y, p = self.x[block], self.p[block, block]
        if feature.size == EUCLIDEAN_SIZE:
            return MapPoint(feature.id, y.copy(), p.copy(), 'euclidean', active, feature.source)
        assert feature.reference is not None
        if y[5] <= 0.0:  # beyond infinity: a point far along the ray, no covariance
            ray, _ = ray_from_angles(feature.reference, float(y[3]), float(y[4]))
            return MapPoint(feature.id, y[:3] + FAR_M * ray, None, 'inverse_depth', active,
                            feature.source)  # fmt: skip
        point, jacobian = euclidean_point(y, feature.reference)
        known_depth = y[5] > 3.0 * math.sqrt(max(p[5, 5], 0.0))
        covariance = jacobian @ p @ jacobian.T if known_depth else None
        return MapPoint(feature.id, point, covariance, 'inverse_depth', active, feature.source)

    def remember_pose(self, stamp_ns: int, frame: int, current: int) -> None:
        """Remember the current pose error (image ``frame`` at ``stamp_ns``) for ``history``."""
        self._history_rows()
        kept = [k for k, earlier in enumerate(self.history_frames) if keeps_pose(current, earlier)]
        columns = (6 * np.array(kept, dtype=np.intp)[:, None] + np.arange(6)).ravel()
        column = self.p[:, :CAMERA_SIZE] @ self.pose_jacobian().T  # (n, 6)
        self.history = np.hstack([self.history[:, columns], column])
        self.history_stamps = [self.history_stamps[k] for k in kept] + [stamp_ns]
        self.history_frames = [self.history_frames[k] for k in kept] + [frame]

    def carried_history(self) -> FloatArray | None:
        """The history when it covers x, else None."""
        return self.history if self.history.shape[0] == len(self.x) else None

    def _history_rows(self) -> FloatArray:
        """The history, emptied when it does not cover x (a state set from outside)."""
        if self.history.shape[0] != len(self.x):
            self.history, self.history_stamps = np.zeros((len(self.x), 0)), []
            self.history_frames = []
        return self.history

    def pose_jacobian(self) -> FloatArray:
        """d(position, rotation about the world axes)/d(camera state) (6, 13)."""
        to_pose = np.zeros((6, CAMERA_SIZE))
        to_pose[:3, R_SLICE] = np.eye(3)
        to_pose[3:, Q_SLICE] = world_angle_jacobian(self.x[Q_SLICE])
        return to_pose

    def pose_covariance(self) -> FloatArray:
        """The camera pose covariance (6, 6): position, rotation about the world axes."""
        to_pose = self.pose_jacobian()
        covariance = to_pose @ self.p[:CAMERA_SIZE, :CAMERA_SIZE] @ to_pose.T
        return np.asarray(0.5 * (covariance + covariance.T), dtype=np.float64)


def _without_block(matrix: FloatArray, start: int, end: int) -> FloatArray:
    """Return the square ``matrix`` without its rows and columns start..end-1."""
    n = len(matrix)
    out = np.empty((n - (end - start), n - (end - start)))
    out[:start, :start] = matrix[:start, :start]
    out[:start, start:] = matrix[:start, end:]
    out[start:, :start] = matrix[end:, :start]
    out[start:, start:] = matrix[end:, end:]
    return out
