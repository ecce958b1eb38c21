"""The MonoSLAM filter: one EKF over the camera and its map of static point features.

Frames, map management, start and loss; the per-frame steps and the modules they use:
docs/design/monoslam_core.md (reasons: docs/design/monoslam.md).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_checks import (
    handover_problem,
    in_view_mask,
    known_disagreement,
    tracking_lost_reason,
    validated_frame,
)
from monoslam_shadow_node.monoslam.core.monoslam_ekf import (
    UpdateOutcome,
    pose_cross,
    predict,
    predicted_measurements,
)
from monoslam_shadow_node.monoslam.core.monoslam_init import (
    MIN_KNOWN_POINTS,
    camera_from_known_points,
    depth_start_features,
    depth_start_pose,
)
from monoslam_shadow_node.monoslam.core.monoslam_intake import (
    farthest_first,
    handover_inverse_depth,
    wanted,
)
from monoslam_shadow_node.monoslam.core.monoslam_model import (
    CAMERA_SIZE,
    Q_SLICE,
    R_SLICE,
    V_SLICE,
    W_SLICE,
)
from monoslam_shadow_node.monoslam.core.monoslam_state import FeatureBlock, FilterState
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    LOST,
    TRACKING,
    WAITING,
    MapPoint,
    MonoSlamConfig,
    MonoSlamFrame,
    MonoSlamResult,
    UpdateCounts,
)
from monoslam_shadow_node.monoslam.core.monoslam_update import slam_update
from monoslam_shadow_node.monoslam.core.monoslam_views import TemplateViews, prediction_warps
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import rotation_from_quaternion as rotation

MAX_HANDOVER_AGE_FRAMES = 30
"""A handover whose feature is not observed within this many frames is dropped."""
MAX_MOVING_IDS = 10_000
"""Features known to move that are remembered (``mark_moving``), the newest kept."""


@dataclass
class _Handover:  # a STATIC feature the Shadow filter handed over, until SLAM takes it
    id: int
    position: FloatArray
    covariance: FloatArray
    frame: int


class MonoSlam:
    """The MonoSLAM filter for one camera. Feed frames in stamp order with ``process``."""

    def __init__(self, camera: CameraModel, config: MonoSlamConfig | None = None) -> None:
        self.camera = camera
        self.config = config or MonoSlamConfig()
        self._known = {int(k): np.asarray(v, float) for k, v in self.config.known_points.items()}
        self._known_keys = np.array(sorted(self._known), dtype=np.int64)
        self._state = FilterState()
        self._views = TemplateViews()  # where each track's template was captured
        self._retired: dict[int, MapPoint] = {}
        self._handovers: dict[int, _Handover] = {}
        self._owned_ids: set[int] = set()
        self._moving_ids: dict[int, None] = {}  # insertion-ordered set, oldest first
        self._revoked_by_shadow: list[int] = []
        self._frame = -1
        self._last_stamp_ns: int | None = None
        self._status = WAITING
        self._idle_frames = 0
        self._known_rejected_frames = 0
        self._known_rejected = (0, 0)  # (rejected, in view) in the latest such frame
        self._rng = np.random.default_rng(self.config.ransac_seed)
        self._slam_update = slam_update(self.config.update)
        self._lost_pose: FloatArray | None = None  # a depth re-start keeps the world

    @property
    def status(self) -> str:
        """'waiting' (for the known points), 'tracking' or 'lost' (in the frame it happened)."""
        return self._status

    @property
    def owned_ids(self) -> frozenset[int]:
        """Track ids SLAM owns (in its map now or before); the Shadow filter ignores them."""
        return frozenset(self._owned_ids)

    @property
    def undecided_ids(self) -> frozenset[int]:
        """Features in the state that filled the map undecided (``fill_undecided``)."""
        if self.config.initialize != 'handover':
            return frozenset()
        return frozenset(f.id for f in self._state.features if not f.cleared)

    @property
    def state_size(self) -> int:
        """Length of the state vector (13 + 6 or 3 per feature, + 2 per tracker offset)."""
        return len(self._state.x)

    def set_camera(self, camera: CameraModel) -> None:
        """Use new intrinsics from the next frame on (a camera_info change)."""
        self.camera = camera

    def set_noise(self, config: MonoSlamConfig) -> None:
        """Measure with ``config`` (another tracking noise) from now on."""
        self.config = config
        self._slam_update = slam_update(config.update)
        for feature in self._state.features if config.offset_states else []:
            self._state.add_offset(feature, config.tracking_offset_px)

    def add_handover(
        self, feature_id: int, position_m: FloatArray, covariance_m2: FloatArray
    ) -> str | None:
        """Queue a handover: position (3,) m, covariance (3, 3); return why refused, or None."""
        position = np.asarray(position_m, dtype=np.float64).reshape(-1)
        covariance = np.asarray(covariance_m2, dtype=np.float64)
        problem = handover_problem(feature_id, position, covariance)
        if problem is not None:
            return problem
        if feature_id in self._owned_ids:
            self._clear(feature_id)
            return None
        if self.config.initialize != 'handover':
            mode = self.config.initialize
            return f'handover of feature {feature_id}: ignored (initialize={mode})'
        self._handovers[feature_id] = _Handover(feature_id, position, covariance, self._frame)
        self._moving_ids.pop(feature_id, None)
        return None

    def _clear(self, feature_id: int) -> None:
        """Clear an undecided feature handed over as STATIC (it leaves probation once linear)."""
        for feature in self._state.features:
            if feature.id == feature_id and not feature.cleared:
                feature.cleared = True
                feature.probation &= self.config.handover_probation and (
                    feature.reference is not None
                )
                self._moving_ids.pop(feature_id, None)

    def mark_moving(self, ids: Iterable[int]) -> None:
        """Note features found DYNAMIC (or revoked); those in the state are revoked."""
        for feature_id in ids:
            self._moving_ids.pop(int(feature_id), None)
            self._moving_ids[int(feature_id)] = None
        moving = set(self._moving_ids) & self.undecided_ids
        for feature in [f for f in self._state.features if f.id in moving]:
            self._revoked_by_shadow.append(feature.id)  # reported with the next frame
            self._remove(feature, retire=False)
            self._owned_ids.discard(feature.id)
        while len(self._moving_ids) > MAX_MOVING_IDS:
            del self._moving_ids[next(iter(self._moving_ids))]

    def map_points(self) -> list[MapPoint]:
        """Return the map: features in the filter, then retired ones."""
        active = [self._state.map_point(feature, True) for feature in self._state.features]
        return active + list(self._retired.values())

    def camera_state(self) -> tuple[FloatArray, FloatArray]:
        """Return the camera state (13,) and its covariance (13, 13) (empty while waiting)."""
        x, p = self._state.x, self._state.p
        return x[:CAMERA_SIZE].copy(), p[:CAMERA_SIZE, :CAMERA_SIZE].copy()

    def predictions(
        self, stamp_ns: int, ids: list[int] | None = None
    ) -> tuple[IntArray, FloatArray, FloatArray, FloatArray]:
        """Return ids (M,), pixels (M, 2), covariances (M, 2, 2) px^2 and warps (M, 2, 2) at
        ``stamp_ns``; zeros for features not predicted in view."""
        if self._status != TRACKING or self._last_stamp_ns is None:
            nothing = np.zeros((0, 2, 2))
            return np.zeros(0, np.int64), np.zeros((0, 2)), nothing, nothing.copy()
        dt_s = max((stamp_ns - self._last_stamp_ns) * 1e-9, 0.0)
        ids_out, pixels, covariances, camera = predicted_measurements(
            self._state, self.camera, dt_s, self.config, ids
        )
        in_view = in_view_mask(self._state, self.camera, self.config, ids_out, pixels)
        covariances[~in_view] = 0.0
        warps = np.zeros((len(ids_out), 2, 2))
        warps[in_view] = prediction_warps(
            self._views, self._state, self.camera, camera, ids_out[in_view]
        )
        return ids_out, pixels, covariances, warps

    # --- the frame loop --------------------------------------------------------------------

    def process(self, frame: MonoSlamFrame) -> MonoSlamResult:
        """Run one frame; MonoSlamInputError (filter unchanged) for a stale stamp or bad arrays."""
        ids, pixels, known_keys, known_pixels, warnings = validated_frame(
            frame, self._last_stamp_ns, self._known_keys
        )
        self._frame += 1
        if self._status != TRACKING and self.config.known_points_source == 'depth':
            return self._try_depth_start(frame, warnings)
        if self._status != TRACKING:
            return self._try_start(frame.stamp_ns, known_keys, known_pixels, warnings)
        assert self._last_stamp_ns is not None
        dt_s = (frame.stamp_ns - self._last_stamp_ns) * 1e-9
        if dt_s > self.config.max_gap_s:
            warnings.append(f'{dt_s:.2f} s since the last frame (more than max_gap_s)')
        self._state.remember_pose(self._last_stamp_ns, self._frame - 1, self._frame)
        predict(self._state, dt_s, self.config)
        self._last_stamp_ns = frame.stamp_ns
        observed = {int(i): pixels[k] for k, i in enumerate(ids)}
        outcome = self._update(observed, known_keys, known_pixels)
        cross = pose_cross(self._state)  # the pose error's covariance with earlier ones'
        measured, rejected, known_used = outcome.measured, outcome.rejected, outcome.known_used
        unseen = [feature for feature in self._state.features if feature.id not in observed]
        searchable = set(self._in_view(unseen).tolist())  # predicted in view, not seen
        removed = self._manage_map(observed, rejected, searchable)
        removed.update(dict.fromkeys(self._revoked_by_shadow, 'revoked'))
        self._revoked_by_shadow.clear()
        seen = set(measured)  # those on probation do not fix the camera
        trusted = [f.id for f in self._state.features if f.id in seen and not f.probation]
        removed.update(self._make_room(observed, measured, trusted, searchable))
        added = self._add_features(observed, measured, trusted)
        in_state = {feature.id for feature in self._state.features}
        self._views.observe(observed, self._state.x[:CAMERA_SIZE], in_state)
        if measured or known_used:
            self._idle_frames = 0
        else:
            self._idle_frames += 1
        in_view = len(known_keys)
        points = [self._known[int(key)] for key in known_keys]
        disagree = known_disagreement(self.camera, self._state, points, known_pixels, self.config)
        if in_view >= MIN_KNOWN_POINTS and (in_view - known_used > in_view / 2 or disagree):
            self._known_rejected_frames += 1
            self._known_rejected = (in_view - known_used, in_view)
        else:
            self._known_rejected_frames = 0
        lost_reason = tracking_lost_reason(
            self._state, self.config, self._idle_frames, self._known_rejected_frames,
            self._known_rejected,
        )  # fmt: skip
        if lost_reason is not None:
            warnings.append(f'tracking lost: {lost_reason}; waiting for the known points')
            removed.update({feature.id: 'lost' for feature in self._state.features})
            result = self._result(frame.stamp_ns, LOST, measured, rejected, added, removed,
                                  known_used, warnings, outcome.counts)  # fmt: skip
            self._reset()
            return result
        result = self._result(frame.stamp_ns, TRACKING, measured, rejected, added, removed,
                              known_used, warnings, outcome.counts)  # fmt: skip
        searched = sorted(i for i in searchable if i not in removed)
        return dataclasses.replace(
            result, searched_ids=searched, state_features=len(self._state.features),
            pose_cross_stamps=cross[0], pose_cross_covariances=cross[1],
        )  # fmt: skip

    # --- steps -----------------------------------------------------------------------------

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
        self._state.start(
            fix.pose_state,
            fix.pose_covariance,
            config.initial_velocity_sigma_m_s,
            config.initial_angular_velocity_sigma_rad_s,
        )
        self._status = TRACKING
        self._idle_frames = 0
        self._known_rejected_frames = 0
        warnings.append(
            f'started from {fix.points} known points (RMS reprojection {fix.rms_error_px:.2f} px)'
        )
        return self._result(stamp_ns, TRACKING, [], [], [], {}, fix.points, warnings)

    def _try_depth_start(self, frame: MonoSlamFrame, warnings: list[str]) -> MonoSlamResult:
        """Start from the features with a measured depth, or report waiting for them."""
        config, stamp_ns = self.config, frame.stamp_ns
        self._last_stamp_ns = stamp_ns
        start = None
        if frame.depths_m is not None:
            start = depth_start_features(
                self.camera, frame.ids, frame.pixels, frame.depths_m, config.depth_noise_per_m,
                config.depth_start_points, config.min_new_spacing_px,
            )  # fmt: skip
        found = 0 if start is None else len(start.ids)
        if start is None or found < MIN_KNOWN_POINTS:
            self._status = WAITING
            warnings.append(f'waiting for the initialization target: {found} features with a '
                            f'depth (at least {MIN_KNOWN_POINTS} needed)')  # fmt: skip
            return self._result(stamp_ns, WAITING, [], [], [], {}, 0, warnings)
        pose, covariance = depth_start_pose(self._lost_pose)
        self._state.start(pose, covariance, config.initial_velocity_sigma_m_s,
                          config.initial_angular_velocity_sigma_rad_s)  # fmt: skip
        added = []
        for i, pixel, rho, variance in zip(start.ids.tolist(), start.pixels, start.rho,
                                           start.rho_variance, strict=True):  # fmt: skip
            if self._state.insert_inverse_depth(
                self.camera, i, pixel, float(rho), float(variance), config.pixel_sigma_px,
                'start', self._frame, config.tracking_offset_px,
            ):  # fmt: skip
                self._owned_ids.add(i)
                added.append(i)
        self._status, self._idle_frames = TRACKING, 0
        warnings.append(f'started from {len(added)} features with a depth')
        return self._result(stamp_ns, TRACKING, [], [], added, {}, 0, warnings)

    def _update(
        self, observed: dict[int, FloatArray], keys: IntArray, known_pixels: FloatArray
    ) -> UpdateOutcome:
        """Update with owned features and known points; return measured, rejected, known used."""
        known = [
            (self._known[key], pixel)
            for key, pixel in zip(keys.tolist(), known_pixels, strict=True)
        ]
        return self._slam_update(self._state, self.camera, observed, known, self.config, self._rng)

    def _manage_map(
        self, observed: dict[int, FloatArray], rejected: list[int], in_view: set[int]
    ) -> dict[int, str]:
        """Count searches, drop failing features, convert linear ones; return removed ids, why."""
        config = self.config
        removed: dict[int, str] = {}
        state = self._state
        refused = set(rejected)
        # a frame without any feature (a covered lens, a dropped image) searches nothing
        searched = in_view if observed else set()
        window, ratio = config.failure_window, config.min_success_ratio
        for feature in list(state.features):
            if feature.id in observed:
                feature.last_seen_frame = self._frame
                feature.searches, feature.found = feature.searches + 1, feature.found + 1
            else:  # not measured in this frame: the run of failures ends
                feature.consecutive_failures = 0
                feature.searches += int(feature.id in searched)  # predicted in view, not found
            if feature.id in refused:  # perhaps the tracker's offset jumped: forget it
                state.reset_offset(feature, config.tracking_offset_px)
            failing = feature.consecutive_failures >= config.max_consecutive_failures or (
                feature.attempts >= window and feature.successes < ratio * feature.attempts
            )
            not_found = feature.searches >= window and feature.found < ratio * feature.searches
            not_found &= feature.source != 'start'  # the known points stay, to be found again
            if failing and config.initialize == 'handover':
                # revoked: it moved after all (handed over, or filling the map undecided);
                # the Shadow filter takes it back, and it fills the map no more
                removed[feature.id] = 'revoked'
                self._remove(feature, retire=False)
                self._owned_ids.discard(feature.id)
                self.mark_moving([feature.id])
            elif failing or not_found:
                removed[feature.id] = 'failed'
                self._remove(feature, retire=False)
        for feature in state.convert_linear(config.linearity_threshold):
            feature.probation &= not feature.cleared  # SLAM's own views fix it now
        return removed

    def _in_view(self, features: list[FeatureBlock]) -> IntArray:
        """Return the ids (M,) of ``features`` predicted in view (``in_view_mask``)."""
        if not features:
            return np.zeros(0, np.int64)
        ids, pixels, _, _ = predicted_measurements(
            self._state, self.camera, 0.0, self.config, [feature.id for feature in features],
            covariances=False,
        )  # fmt: skip
        return ids[in_view_mask(self._state, self.camera, self.config, ids, pixels)]

    def _make_room(
        self,
        observed: dict[int, FloatArray],
        measured: list[int],
        trusted: list[int],
        in_view: set[int],
    ) -> dict[int, str]:
        """Evict out-of-view features into the frozen map while the state is too full."""
        config = self.config
        excess = len(self._state.features) + sum(self._wanted(observed, measured, trusted))
        excess -= config.max_features
        if excess <= 0:
            return {}
        unseen = [f for f in self._state.features if f.id not in observed and f.source != 'start']
        away = sorted(
            (feature for feature in unseen if feature.id not in in_view),
            key=lambda feature: (feature.successes, feature.last_seen_frame),
        )
        evicted: dict[int, str] = {}
        for feature in away[:excess]:
            evicted[feature.id] = 'evicted'
            self._remove(feature, retire=True)
        return evicted

    def _wanted(
        self, observed: dict[int, FloatArray], measured: list[int], trusted: list[int]
    ) -> tuple[int, int]:
        """The handovers and new features this frame would add (``monoslam_intake.wanted``)."""
        seen = set(measured)
        cleared = sum(1 for f in self._state.features if f.id in seen and f.cleared)
        offered = sum(1 for i in self._handovers if i in observed)
        return wanted(self.config, offered, len(measured), cleared, len(trusted))

    def _add_features(
        self, observed: dict[int, FloatArray], measured: list[int], trusted: list[int]
    ) -> list[int]:
        """Add handovers, then new features (``monoslam_intake``); return their ids."""
        config = self.config
        room = config.max_features - len(self._state.features)
        take, budget = self._wanted(observed, measured, trusted)
        added: list[int] = []
        for feature_id, handover in list(self._handovers.items()):
            if self._frame - handover.frame > MAX_HANDOVER_AGE_FRAMES:
                del self._handovers[feature_id]
            elif feature_id in observed and len(added) < min(room, take):
                del self._handovers[feature_id]
                if self._insert(feature_id, observed[feature_id], handover):
                    added.append(feature_id)
        budget = min(budget, room - len(added))
        excluded = (self._owned_ids, self._moving_ids, self._handovers)
        candidates = [i for i in observed if not any(i in ids for ids in excluded)]
        if budget <= 0 or not candidates:
            return added
        pixels = np.array([observed[i] for i in candidates])
        taken = np.array([observed[i] for i in measured + added]).reshape(-1, 2)
        new = farthest_first(
            pixels, taken, budget, config.min_new_spacing_px,
            lambda k: self._insert(candidates[k], pixels[k], None),
        )  # fmt: skip
        return added + [candidates[k] for k in new]

    def _insert(self, feature_id: int, pixel: FloatArray, handover: _Handover | None) -> bool:
        """Append an inverse-depth feature seen at ``pixel``; True if it went in."""
        rho = self.config.initial_inverse_depth
        rho_variance = self.config.initial_inverse_depth_sigma**2
        if handover is not None:
            start = handover_inverse_depth(
                handover.position, handover.covariance, self._state.x[R_SLICE], rho_variance
            )
            if start is None:
                return False
            rho, rho_variance = start
        source = 'handover' if handover is not None else 'new'
        inserted = self._state.insert_inverse_depth(
            self.camera, feature_id, pixel, rho, rho_variance, self.config.pixel_sigma_px,
            source, self._frame, self.config.tracking_offset_px,
        )  # fmt: skip
        if inserted:
            self._owned_ids.add(feature_id)
            feature = self._state.features[-1]
            # on probation: undecided ones until cleared, the others until linear (module doc)
            feature.cleared = handover is not None or self.config.initialize != 'handover'
            feature.probation = (
                (not feature.cleared and self.config.undecided_probation)
                or (handover is not None and self.config.handover_probation)
                or (self.config.initialize == 'all' and self.config.new_probation)
            )
        return inserted

    def _remove(self, feature: FeatureBlock, *, retire: bool) -> None:
        """Take a feature out of the state (into the frozen map when ``retire``)."""
        if retire:
            self._retired[feature.id] = self._state.map_point(feature, False)
        self._state.remove(feature)

    def _reset(self) -> None:
        """Retire the map and wait for the known points again."""
        self._lost_pose = self._state.x[:7].copy() if len(self._state.x) >= 7 else None
        for feature in list(self._state.features):
            self._remove(feature, retire=True)
        self._state.x = np.zeros(0)
        self._state.p = np.zeros((0, 0))
        self._handovers.clear()
        self._views.clear()
        self._status = WAITING
        self._idle_frames = 0

    # --- outputs ---------------------------------------------------------------------------

    def _result(
        self, stamp_ns: int, status: str, measured: list[int], rejected: list[int],
        added: list[int], removed: dict[int, str], known_used: int, warnings: list[str],
        counts: UpdateCounts | None = None,
    ) -> MonoSlamResult:  # fmt: skip
        counts = counts or UpdateCounts()
        if status == WAITING or len(self._state.x) < CAMERA_SIZE:
            return MonoSlamResult(
                stamp_ns, self._frame, status, None, None, None, None, None, measured,
                rejected, added, removed, known_used, warnings, counts,
            )  # fmt: skip
        x, q = self._state.x, self._state.x[Q_SLICE]
        return MonoSlamResult(
            stamp_ns, self._frame, status, rotation(q), x[R_SLICE].copy(),
            self._state.pose_covariance(), x[V_SLICE].copy(), x[W_SLICE].copy(), measured,
            rejected, added, removed, known_used, warnings, counts,
        )  # fmt: skip
