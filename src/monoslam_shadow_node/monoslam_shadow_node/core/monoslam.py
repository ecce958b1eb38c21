"""The MonoSLAM filter: one EKF over the camera and its map of static point features
(``monoslam_model`` has the state, the models and their Jacobians).

Per frame (``MonoSlam.process``):

1. until started: wait for the known points (``MonoSlamConfig.known_points``) to be in view,
   then take the camera pose from them (``monoslam_init``);
2. predict with the constant velocity model;
3. predict every owned feature and every known point in view, with its innovation
   covariance S_i = H_i P H_i^T + R (the active search region: the tracker may use the
   predicted pixel, ``MonoSlam.predictions``); a measurement whose Mahalanobis distance
   exceeds the chi-square gate is rejected (counted against the feature);
4. update with all accepted measurements at once, Joseph form
   P = (I - K H) P (I - K H)^T + K R K^T, then renormalize the quaternion (with its Jacobian);
5. map management: inverse-depth features whose linearity index allows it become Euclidean;
   features failing too often are deleted; features no longer tracked are retired to the
   frozen map (ids are never reused, so they cannot be measured again); new features are added
   - in ``initialize='all'`` (classic MonoSLAM, the paper's Fig. 5(a), (b)) from every new
   track, undelayed, with the inverse-depth prior, while fewer than ``target_measured``
   features were measured; in ``initialize='handover'`` (with the Shadow filter, Fig. 5(c))
   only from features handed over as STATIC (``add_handover``): the ray of the current
   measurement anchored at the current camera, the inverse depth and its variance from the
   handed-over point and covariance. The map never holds more than ``max_features``;
6. tracking is lost when no measurement was accepted for ``lost_after_frames`` frames, the
   camera's position uncertainty exceeds ``max_position_sigma_m``, or the gate rejected more
   than half of the known points in view (at least ``MIN_KNOWN_POINTS`` of them) in
   ``lost_after_known_rejected_frames`` frames in a row: known points are certain, so an
   estimate they disagree with has diverged (e.g. dragged along by moving features), even
   while its grown covariance lets a few of them through now and then; or when the pose
   covariance collapsed (``MIN_POSE_EIGENVALUE_RATIO``). The filter reports it, retires its
   map and starts again from the known points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.core.monoslam_init import MIN_KNOWN_POINTS, camera_from_known_points
from monoslam_shadow_node.core.monoslam_model import (
    CAMERA_SIZE,
    EUCLIDEAN_SIZE,
    INVERSE_DEPTH_SIZE,
    Q_SLICE,
    R_SLICE,
    V_SLICE,
    W_SLICE,
    FloatArray,
    euclidean_point,
    linearity_index,
    new_inverse_depth_feature,
    predict_camera,
    project_feature,
    ray_from_angles,
)
from monoslam_shadow_node.core.projective import chi2_quantile
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import rotation_from_quaternion as rotation
from slam_core.geometry.quaternion import world_angle_jacobian

IntArray = NDArray[np.int64]
WAITING, TRACKING, LOST = 'waiting', 'tracking', 'lost'
INITIALIZE_MODES = ('all', 'handover')
FAR_M = 1000.0
"""Where along its ray an inverse-depth feature with rho <= 0 is reported (m)."""
MAX_HANDOVER_AGE_FRAMES = 30
"""A handover whose feature is not observed within this many frames is dropped."""
MIN_POSE_EIGENVALUE_RATIO = 1e-12
"""Tracking is lost when the pose covariance's smallest eigenvalue is not above this share of
its largest: numerically singular, or not positive definite (measured in tracking: ~1e-4)."""


class MonoSlamInputError(ValueError):
    """A frame the filter cannot use (the message names the culprit); the filter is unchanged."""


@dataclass(frozen=True)
class MonoSlamConfig:
    """Noise, gating, map management and initialization settings (module docstring).

    ``known_points`` maps a key (e.g. 4 marker id + corner index) to a world point (3,) m.
    """

    known_points: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    pixel_sigma_px: float = 1.0
    linear_acceleration_sigma: float = 2.0  # m/s^2/sqrt(Hz)
    angular_acceleration_sigma: float = 8.0  # rad/s^2/sqrt(Hz): hand tremor at 2-6 Hz
    initial_velocity_sigma_m_s: float = 0.5
    initial_angular_velocity_sigma_rad_s: float = 0.5
    initial_inverse_depth: float = 0.2  # 1/m
    initial_inverse_depth_sigma: float = 0.3  # 1/m
    gate_probability: float = 0.999
    linearity_threshold: float = 0.1
    max_features: int = 50
    target_measured: int = 25
    max_new_per_frame: int = 5
    min_new_spacing_px: float = 20.0
    max_unseen_frames: int = 2
    failure_window: int = 10
    min_success_ratio: float = 0.5
    max_consecutive_failures: int = 3
    lost_after_frames: int = 15
    lost_after_known_rejected_frames: int = 3
    max_position_sigma_m: float = 2.0
    max_gap_s: float = 1.0
    initialize: str = 'all'

    def __post_init__(self) -> None:
        """Reject values the filter cannot honour; the message names the field."""
        positive = (
            'pixel_sigma_px', 'linear_acceleration_sigma', 'angular_acceleration_sigma',
            'initial_velocity_sigma_m_s', 'initial_angular_velocity_sigma_rad_s',
            'initial_inverse_depth', 'initial_inverse_depth_sigma', 'linearity_threshold',
            'max_position_sigma_m', 'max_gap_s',
        )  # fmt: skip
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0.0):
                raise ValueError(f'{name}={value!r}: must be a finite number > 0')
        for name in ('gate_probability', 'min_success_ratio'):
            value = getattr(self, name)
            if not 0.0 < value < 1.0:
                raise ValueError(f'{name}={value!r}: must be in (0, 1)')
        counts = (
            'max_features', 'target_measured', 'max_new_per_frame', 'max_unseen_frames',
            'failure_window', 'max_consecutive_failures', 'lost_after_frames',
            'lost_after_known_rejected_frames',
        )  # fmt: skip
        for name in counts:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f'{name}={value!r}: must be an integer >= 1')
        if self.min_new_spacing_px < 0.0:
            raise ValueError(f'min_new_spacing_px={self.min_new_spacing_px!r}: must be >= 0')
        if self.initialize not in INITIALIZE_MODES:
            raise ValueError(
                f'initialize={self.initialize!r}: must be one of {", ".join(INITIALIZE_MODES)}'
            )
        for key, point in self.known_points.items():
            if len(point) != 3 or not all(math.isfinite(float(c)) for c in point):
                raise ValueError(f'known point {key}: {point!r} must be 3 finite coordinates (m)')

    @property
    def gate(self) -> float:
        """The chi-square gate (2 degrees of freedom) on one feature's innovation."""
        return chi2_quantile(self.gate_probability, 2)


@dataclass(frozen=True, eq=False)
class MonoSlamFrame:
    """One image's measurements: track ids (N,) and raw pixels (N, 2) of tracked features, and
    known-point keys (T,) with their raw pixels (T, 2)."""

    stamp_ns: int
    ids: IntArray
    pixels: FloatArray
    known_keys: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    known_pixels: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass(frozen=True, eq=False)
class MapPoint:
    """A map feature in the world frame: id, position (3,) m and covariance (3, 3) m^2
    (None while an inverse-depth feature's depth is not known: rho within 3 sigma of 0),
    its parametrization ('inverse_depth' or 'euclidean'), whether it is in the filter (or
    retired) and how it entered ('new' or 'handover')."""

    id: int
    position: FloatArray
    covariance: FloatArray | None
    parametrization: str
    active: bool
    source: str


@dataclass(frozen=True, eq=False)
class MonoSlamResult:
    """What one frame produced. ``rotation`` (3, 3) R_world_camera and ``centre`` (3,) m are
    None while waiting; ``pose_covariance`` (6, 6) is over (position, rotation about the world
    axes), the convention of geometry_msgs/PoseWithCovariance; velocities in the world
    (linear, m/s) and camera (angular, rad/s) frames."""

    stamp_ns: int
    frame: int
    status: str
    rotation: FloatArray | None
    centre: FloatArray | None
    pose_covariance: FloatArray | None
    linear_velocity: FloatArray | None
    angular_velocity: FloatArray | None
    measured_ids: list[int]
    rejected_ids: list[int]
    added_ids: list[int]
    removed: dict[int, str]
    known_points_used: int
    warnings: list[str]


@dataclass
class _Feature:
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


@dataclass
class _Handover:
    id: int
    position: FloatArray
    covariance: FloatArray
    frame: int


class MonoSlam:
    """The MonoSLAM filter for one camera. Feed frames in stamp order with ``process``."""

    def __init__(self, camera: CameraModel, config: MonoSlamConfig | None = None) -> None:
        self.camera = camera
        self.config = config or MonoSlamConfig()
        self._known = {int(k): np.asarray(v, dtype=np.float64)
                       for k, v in self.config.known_points.items()}  # fmt: skip
        self._x = np.zeros(0)
        self._p = np.zeros((0, 0))
        self._features: list[_Feature] = []
        self._retired: dict[int, MapPoint] = {}
        self._handovers: dict[int, _Handover] = {}
        self._owned_ids: set[int] = set()
        self._frame = -1
        self._last_stamp_ns: int | None = None
        self._status = WAITING
        self._idle_frames = 0
        self._known_rejected_frames = 0
        self._known_rejected = (0, 0)  # (rejected, in view) in the latest such frame

    # --- public state ----------------------------------------------------------------------

    @property
    def status(self) -> str:
        """'waiting' (for the known points), 'tracking' or 'lost' (in the frame it happened)."""
        return self._status

    @property
    def owned_ids(self) -> frozenset[int]:
        """Track ids SLAM owns (in its map now or before); the Shadow filter ignores them."""
        return frozenset(self._owned_ids)

    @property
    def state_size(self) -> int:
        """Length of the state vector (13 + 6 per inverse-depth + 3 per Euclidean feature)."""
        return len(self._x)

    def set_camera(self, camera: CameraModel) -> None:
        """Use new intrinsics from the next frame on (a camera_info change)."""
        self.camera = camera

    def add_handover(
        self, feature_id: int, position_m: FloatArray, covariance_m2: FloatArray
    ) -> str | None:
        """Queue a feature handed over as STATIC (world position (3,) m, covariance (3, 3));
        it enters the map when next observed. Return why it was refused, or None."""
        position = np.asarray(position_m, dtype=np.float64).reshape(-1)
        covariance = np.asarray(covariance_m2, dtype=np.float64)
        if position.shape != (3,) or not np.all(np.isfinite(position)):
            return f'handover of feature {feature_id}: position {position.tolist()} not finite'
        if covariance.shape != (3, 3) or not np.all(np.isfinite(covariance)):
            return f'handover of feature {feature_id}: covariance not a finite 3x3 matrix'
        if np.min(np.linalg.eigvalsh(0.5 * (covariance + covariance.T))) < 0.0:
            return f'handover of feature {feature_id}: covariance not positive semi-definite'
        if feature_id in self._owned_ids:
            return None
        if self.config.initialize != 'handover':
            mode = self.config.initialize
            return f'handover of feature {feature_id}: ignored (initialize={mode})'
        self._handovers[feature_id] = _Handover(feature_id, position, covariance, self._frame)
        return None

    def map_points(self) -> list[MapPoint]:
        """Return the map: features in the filter, then retired ones."""
        active = [self._map_point(feature, True) for feature in self._features]
        return active + list(self._retired.values())

    def camera_state(self) -> tuple[FloatArray, FloatArray]:
        """Return the camera state (13,) and its covariance (13, 13) (empty while waiting)."""
        return self._x[:CAMERA_SIZE].copy(), self._p[:CAMERA_SIZE, :CAMERA_SIZE].copy()

    def predictions(
        self, stamp_ns: int, ids: list[int] | None = None
    ) -> tuple[IntArray, FloatArray, FloatArray]:
        """Return the owned features' predicted raw pixels at ``stamp_ns``: ids (M,), pixels
        (M, 2) and innovation covariances (M, 2, 2) px^2 (the active search regions)."""
        if self._status != TRACKING or self._last_stamp_ns is None:
            return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2))
        dt_s = max((stamp_ns - self._last_stamp_ns) * 1e-9, 0.0)
        camera, f, q = predict_camera(self._x[:CAMERA_SIZE], dt_s, *self._sigmas())
        p_cc = f @ self._p[:CAMERA_SIZE, :CAMERA_SIZE] @ f.T + q
        wanted = None if ids is None else set(ids)
        out_ids, out_pixels, out_s = [], [], []
        for feature in self._features:
            if wanted is not None and feature.id not in wanted:
                continue
            block = slice(feature.start, feature.start + feature.size)
            pixel, h_c, h_f, depth = project_feature(
                self.camera, camera, self._x[block], feature.reference
            )
            if depth <= 0.0:
                continue
            p_cf = f @ self._p[:CAMERA_SIZE, block]
            s = h_c @ p_cc @ h_c.T + 2.0 * h_c @ p_cf @ h_f.T + h_f @ self._p[block, block] @ h_f.T
            out_ids.append(feature.id)
            out_pixels.append(pixel)
            out_s.append(s + self.config.pixel_sigma_px**2 * np.eye(2))
        return (
            np.array(out_ids, dtype=np.int64),
            np.array(out_pixels).reshape(-1, 2),
            np.array(out_s).reshape(-1, 2, 2),
        )

    # --- the frame loop --------------------------------------------------------------------

    def process(self, frame: MonoSlamFrame) -> MonoSlamResult:
        """Run one frame (module docstring). Raises MonoSlamInputError (filter unchanged) for
        a stamp that does not advance or malformed arrays."""
        ids, pixels, known_keys, known_pixels, warnings = self._validated(frame)
        self._frame += 1
        if self._status != TRACKING:
            return self._try_start(frame.stamp_ns, known_keys, known_pixels, warnings)
        assert self._last_stamp_ns is not None
        dt_s = (frame.stamp_ns - self._last_stamp_ns) * 1e-9
        if dt_s > self.config.max_gap_s:
            warnings.append(f'{dt_s:.2f} s since the last frame (more than max_gap_s)')
        self._predict(dt_s)
        self._last_stamp_ns = frame.stamp_ns
        observed = {int(i): pixels[k] for k, i in enumerate(ids)}
        measured, rejected, known_used = self._update(observed, known_keys, known_pixels)
        removed = self._manage_map(observed, measured, rejected)
        added = self._add_features(observed, measured)
        if measured or known_used:
            self._idle_frames = 0
        else:
            self._idle_frames += 1
        in_view = len(known_keys)
        if in_view >= MIN_KNOWN_POINTS and in_view - known_used > in_view / 2:
            self._known_rejected_frames += 1
            self._known_rejected = (in_view - known_used, in_view)
        else:
            self._known_rejected_frames = 0
        lost_reason = self._lost_reason()
        if lost_reason is not None:
            warnings.append(f'tracking lost: {lost_reason}; waiting for the known points')
            result = self._result(frame.stamp_ns, LOST, measured, rejected, added, removed,
                                  known_used, warnings)  # fmt: skip
            self._reset()
            return result
        return self._result(frame.stamp_ns, TRACKING, measured, rejected, added, removed,
                            known_used, warnings)  # fmt: skip

    # --- steps -----------------------------------------------------------------------------

    def _validated(
        self, frame: MonoSlamFrame
    ) -> tuple[IntArray, FloatArray, IntArray, FloatArray, list[str]]:
        """Check stamps and shapes; drop non-finite pixels with a warning."""
        if self._last_stamp_ns is not None and frame.stamp_ns <= self._last_stamp_ns:
            raise MonoSlamInputError(
                f'frame stamp {frame.stamp_ns} ns does not advance past {self._last_stamp_ns} ns'
            )
        ids = np.asarray(frame.ids, dtype=np.int64).reshape(-1)
        pixels = np.asarray(frame.pixels, dtype=np.float64).reshape(-1, 2)
        keys = np.asarray(frame.known_keys, dtype=np.int64).reshape(-1)
        known = np.asarray(frame.known_pixels, dtype=np.float64).reshape(-1, 2)
        if len(ids) != len(pixels) or len(keys) != len(known):
            raise MonoSlamInputError(
                f'{len(ids)} ids for {len(pixels)} pixels, {len(keys)} known-point keys for '
                f'{len(known)} pixels: counts must match'
            )
        warnings = []
        finite = np.all(np.isfinite(pixels), axis=1)
        if not np.all(finite):
            bad = ', '.join(str(int(i)) for i in ids[~finite])
            warnings.append(f'ignored features with non-finite pixels: ids {bad}')
        finite_known = np.all(np.isfinite(known), axis=1) & np.isin(keys, list(self._known))
        return ids[finite], pixels[finite], keys[finite_known], known[finite_known], warnings

    def _sigmas(self) -> tuple[float, float]:
        return self.config.linear_acceleration_sigma, self.config.angular_acceleration_sigma

    def _try_start(
        self, stamp_ns: int, keys: IntArray, pixels: FloatArray, warnings: list[str]
    ) -> MonoSlamResult:
        """Start from the known points in view, or report waiting for them."""
        self._last_stamp_ns = stamp_ns
        fix = None
        if len(keys) >= MIN_KNOWN_POINTS:
            points = np.array([self._known[int(k)] for k in keys])
            fix = camera_from_known_points(self.camera, points, pixels, self.config.pixel_sigma_px)
        if fix is None:
            self._status = WAITING
            warnings.append(
                f'waiting for the initialization target: {len(keys)} of the '
                f'{len(self._known)} known points in view (at least {MIN_KNOWN_POINTS} needed)'
                if self._known
                else 'no known points configured: cannot fix the scale and start'
            )
            return self._result(stamp_ns, WAITING, [], [], [], {}, 0, warnings)
        config = self.config
        self._x = np.zeros(CAMERA_SIZE)
        self._x[:7] = fix.pose_state
        self._p = np.zeros((CAMERA_SIZE, CAMERA_SIZE))
        self._p[:7, :7] = fix.pose_covariance
        self._p[V_SLICE, V_SLICE] = config.initial_velocity_sigma_m_s**2 * np.eye(3)
        self._p[W_SLICE, W_SLICE] = config.initial_angular_velocity_sigma_rad_s**2 * np.eye(3)
        self._features = []
        self._status = TRACKING
        self._idle_frames = 0
        self._known_rejected_frames = 0
        warnings.append(
            f'started from {fix.points} known points (RMS reprojection {fix.rms_error_px:.2f} px)'
        )
        return self._result(stamp_ns, TRACKING, [], [], [], {}, fix.points, warnings)

    def _predict(self, dt_s: float) -> None:
        """Constant velocity prediction of the camera; features are static."""
        camera, f, q = predict_camera(self._x[:CAMERA_SIZE], dt_s, *self._sigmas())
        self._x[:CAMERA_SIZE] = camera
        c = slice(0, CAMERA_SIZE)
        self._p[c, c] = f @ self._p[c, c] @ f.T + q
        self._p[c, CAMERA_SIZE:] = f @ self._p[c, CAMERA_SIZE:]
        self._p[CAMERA_SIZE:, c] = self._p[c, CAMERA_SIZE:].T

    def _update(
        self, observed: dict[int, FloatArray], keys: IntArray, known_pixels: FloatArray
    ) -> tuple[list[int], list[int], int]:
        """Gate and apply all measurements of owned features and known points; return the
        measured and rejected feature ids and the number of known points used."""
        n = len(self._x)
        camera = self._x[:CAMERA_SIZE]
        rows: list[FloatArray] = []
        residuals: list[FloatArray] = []
        measured: list[int] = []
        rejected: list[int] = []
        sigma2 = self.config.pixel_sigma_px**2
        gate = self.config.gate
        c = slice(0, CAMERA_SIZE)
        # (pixel, known point or None, feature or None): known points first, then features
        candidates: list[tuple[FloatArray, FloatArray | None, _Feature | None]] = [
            (pixel, self._known[key], None)
            for key, pixel in zip(keys.tolist(), known_pixels, strict=True)
        ]
        candidates += [(observed[f.id], None, f) for f in self._features if f.id in observed]
        known_used = 0
        for pixel, point, feature in candidates:
            block: slice | None = None
            if feature is None and point is not None:
                predicted, h_c, h_f, depth = project_feature(self.camera, camera, point, None)
            elif feature is not None:
                block = slice(feature.start, feature.start + feature.size)
                predicted, h_c, h_f, depth = project_feature(
                    self.camera, camera, self._x[block], feature.reference
                )
            ok = depth > 0.0
            if ok:
                s = h_c @ self._p[c, c] @ h_c.T + sigma2 * np.eye(2)
                if block is not None:
                    cross = h_c @ self._p[c, block] @ h_f.T
                    s += cross + cross.T + h_f @ self._p[block, block] @ h_f.T
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
            self._joseph_update(np.vstack(rows), np.concatenate(residuals), sigma2)
        return measured, rejected, known_used

    def _joseph_update(self, h: FloatArray, residual: FloatArray, sigma2: float) -> None:
        """x += K nu; P = (I - K H) P (I - K H)^T + K R K^T, R = sigma2 I; renormalize q."""
        ph_t = self._p @ h.T
        s = h @ ph_t + sigma2 * np.eye(len(h))
        gain = np.linalg.solve(s, ph_t.T).T
        self._x = self._x + gain @ residual
        a = np.eye(len(self._x)) - gain @ h
        p = a @ self._p @ a.T + sigma2 * (gain @ gain.T)
        norm = float(np.linalg.norm(self._x[Q_SLICE]))
        q = self._x[Q_SLICE] / norm
        jacobian = (np.eye(4) - np.outer(q, q)) / norm
        self._x[Q_SLICE] = q
        p[Q_SLICE, :] = jacobian @ p[Q_SLICE, :]
        p[:, Q_SLICE] = p[:, Q_SLICE] @ jacobian.T
        self._p = 0.5 * (p + p.T)

    def _manage_map(
        self, observed: dict[int, FloatArray], measured: list[int], rejected: list[int]
    ) -> dict[int, str]:
        """Convert linear-enough features to Euclidean, delete failing ones, retire unseen
        ones; return removed ids with the reason."""
        config = self.config
        removed: dict[int, str] = {}
        for feature in list(self._features):
            if feature.id in observed:
                feature.last_seen_frame = self._frame
            failing = feature.consecutive_failures >= config.max_consecutive_failures or (
                feature.attempts >= config.failure_window
                and feature.successes < config.min_success_ratio * feature.attempts
            )
            if failing:
                removed[feature.id] = 'failed'
                self._remove(feature, retire=False)
            elif self._frame - feature.last_seen_frame > config.max_unseen_frames:
                removed[feature.id] = 'unseen'
                self._remove(feature, retire=True)
        centre = self._x[R_SLICE]
        for feature in self._features:
            if feature.size == INVERSE_DEPTH_SIZE and feature.reference is not None:
                block = slice(feature.start, feature.start + feature.size)
                rho_variance = float(self._p[feature.start + 5, feature.start + 5])
                index = linearity_index(self._x[block], feature.reference, rho_variance, centre)
                if index < config.linearity_threshold and self._x[feature.start + 5] > 0.0:
                    self._to_euclidean(feature)
        return removed

    def _add_features(self, observed: dict[int, FloatArray], measured: list[int]) -> list[int]:
        """Add new features (``initialize`` mode); return their ids."""
        config = self.config
        room = config.max_features - len(self._features)
        if room <= 0:
            return []
        added: list[int] = []
        if config.initialize == 'handover':
            for feature_id, handover in list(self._handovers.items()):
                if self._frame - handover.frame > MAX_HANDOVER_AGE_FRAMES:
                    del self._handovers[feature_id]
                elif feature_id in observed and len(added) < room:
                    del self._handovers[feature_id]
                    if self._insert(feature_id, observed[feature_id], handover):
                        added.append(feature_id)
            return added
        if len(measured) >= config.target_measured:
            return []
        budget = min(room, config.max_new_per_frame, config.target_measured - len(measured))
        candidates = [i for i in observed if i not in self._owned_ids]
        if not candidates:
            return []
        pixels = np.array([observed[i] for i in candidates])
        taken = np.array([observed[i] for i in measured]).reshape(-1, 2)
        # farthest first: each new feature goes where the measured ones leave the largest gap
        gap = np.full(len(candidates), np.inf)
        if len(taken):
            gap = np.min(np.linalg.norm(pixels[:, None] - taken[None], axis=2), axis=1)
        while len(added) < budget:
            best = int(np.argmax(gap))
            if gap[best] < config.min_new_spacing_px:
                break
            gap[best] = -1.0
            if self._insert(candidates[best], pixels[best], None):
                added.append(candidates[best])
                gap = np.minimum(gap, np.linalg.norm(pixels - pixels[best], axis=1))
        return added

    def _insert(self, feature_id: int, pixel: FloatArray, handover: _Handover | None) -> bool:
        """Append an inverse-depth feature seen at ``pixel``; True if it went in."""
        camera = self._x[:CAMERA_SIZE]
        rho = self.config.initial_inverse_depth
        rho_variance = self.config.initial_inverse_depth_sigma**2
        if handover is not None:
            offset = handover.position - camera[R_SLICE]
            depth = float(np.linalg.norm(offset))
            if depth <= 1e-3:
                return False
            direction = offset / depth
            depth_variance = float(direction @ handover.covariance @ direction)
            rho = 1.0 / depth
            rho_variance = depth_variance * rho**4
        feature, reference, d_camera, d_pixel = new_inverse_depth_feature(
            self.camera, camera, pixel, rho
        )
        if not np.all(np.isfinite(feature)):
            return False
        n = len(self._x)
        c = slice(0, CAMERA_SIZE)
        cross = d_camera @ self._p[c, :]  # (6, n)
        block = d_camera @ self._p[c, c] @ d_camera.T
        block += self.config.pixel_sigma_px**2 * (d_pixel @ d_pixel.T)
        block[5, 5] += rho_variance
        p = np.zeros((n + INVERSE_DEPTH_SIZE, n + INVERSE_DEPTH_SIZE))
        p[:n, :n] = self._p
        p[n:, :n] = cross
        p[:n, n:] = cross.T
        p[n:, n:] = block
        self._p = p
        self._x = np.concatenate([self._x, feature])
        source = 'handover' if handover is not None else 'new'
        frame = self._frame
        self._features.append(
            _Feature(feature_id, n, INVERSE_DEPTH_SIZE, reference, source, frame, frame)
        )
        self._owned_ids.add(feature_id)
        return True

    def _to_euclidean(self, feature: _Feature) -> None:
        """Replace an inverse-depth feature's 6 states by its 3 Euclidean ones."""
        assert feature.reference is not None
        start = feature.start
        block = slice(start, start + INVERSE_DEPTH_SIZE)
        point, jacobian = euclidean_point(self._x[block], feature.reference)
        n = len(self._x)
        transform = np.zeros((n - 3, n))
        transform[:start, :start] = np.eye(start)
        transform[start : start + 3, block] = jacobian
        transform[start + 3 :, start + INVERSE_DEPTH_SIZE :] = np.eye(n - start - 6)
        self._x = np.concatenate([self._x[:start], point, self._x[start + INVERSE_DEPTH_SIZE :]])
        p = transform @ self._p @ transform.T
        self._p = 0.5 * (p + p.T)
        feature.size, feature.reference = EUCLIDEAN_SIZE, None
        for other in self._features:
            if other.start > start:
                other.start -= 3

    def _remove(self, feature: _Feature, *, retire: bool) -> None:
        """Take a feature out of the state (into the frozen map when ``retire``)."""
        if retire:
            self._retired[feature.id] = self._map_point(feature, False)
        keep = np.ones(len(self._x), dtype=bool)
        keep[feature.start : feature.start + feature.size] = False
        self._x = self._x[keep]
        self._p = self._p[np.ix_(keep, keep)]
        self._features.remove(feature)
        for other in self._features:
            if other.start > feature.start:
                other.start -= feature.size

    def _lost_reason(self) -> str | None:
        """Return why tracking is lost, or None."""
        if self._idle_frames >= self.config.lost_after_frames:
            return f'no feature or known point measured for {self._idle_frames} frames'
        if self._known_rejected_frames >= self.config.lost_after_known_rejected_frames:
            rejected, in_view = self._known_rejected
            return (
                f'the gate rejected most known points in view ({rejected} of {in_view}) for '
                f'{self._known_rejected_frames} frames: the estimate disagrees with them'
            )
        sigma = math.sqrt(max(float(np.max(np.linalg.eigvalsh(self._p[R_SLICE, R_SLICE]))), 0.0))
        if not math.isfinite(sigma) or sigma > self.config.max_position_sigma_m:
            return f'camera position sigma {sigma:.2f} m exceeds max_position_sigma_m'
        if not np.all(np.isfinite(self._x)):
            return 'the state is not finite'
        values = np.linalg.eigvalsh(self._pose_covariance())
        if not values[0] > MIN_POSE_EIGENVALUE_RATIO * values[-1]:
            return (
                f'the pose covariance collapsed (eigenvalues {values[0]:.1e} to '
                f'{values[-1]:.1e}): the filter is overconfident'
            )
        return None

    def _reset(self) -> None:
        """Retire the map and wait for the known points again."""
        for feature in list(self._features):
            self._remove(feature, retire=True)
        self._x = np.zeros(0)
        self._p = np.zeros((0, 0))
        self._handovers.clear()
        self._status = WAITING
        self._idle_frames = 0

    # --- outputs ---------------------------------------------------------------------------

    def _map_point(self, feature: _Feature, active: bool) -> MapPoint:
        block = slice(feature.start, feature.start + feature.size)
        y, p = self._x[block], self._p[block, block]
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

    def _result(
        self,
        stamp_ns: int,
        status: str,
        measured: list[int],
        rejected: list[int],
        added: list[int],
        removed: dict[int, str],
        known_used: int,
        warnings: list[str],
    ) -> MonoSlamResult:
        if status == WAITING or len(self._x) < CAMERA_SIZE:
            return MonoSlamResult(
                stamp_ns, self._frame, status, None, None, None, None, None, measured,
                rejected, added, removed, known_used, warnings,
            )  # fmt: skip
        x, q = self._x, self._x[Q_SLICE]
        return MonoSlamResult(
            stamp_ns, self._frame, status, rotation(q), x[R_SLICE].copy(),
            self._pose_covariance(), x[V_SLICE].copy(), x[W_SLICE].copy(), measured,
            rejected, added, removed, known_used, warnings,
        )  # fmt: skip

    def _pose_covariance(self) -> FloatArray:
        """The camera pose covariance (6, 6): position, rotation about the world axes."""
        to_pose = np.zeros((6, CAMERA_SIZE))
        to_pose[:3, R_SLICE] = np.eye(3)
        to_pose[3:, Q_SLICE] = world_angle_jacobian(self._x[Q_SLICE])
        covariance = to_pose @ self._p[:CAMERA_SIZE, :CAMERA_SIZE] @ to_pose.T
        return np.asarray(0.5 * (covariance + covariance.T), dtype=np.float64)
