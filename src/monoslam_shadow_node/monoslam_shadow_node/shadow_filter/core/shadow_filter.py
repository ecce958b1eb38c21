"""The Shadow filter (paper 001, section III): one EKF per feature, the static/dynamic
classifier and the feature lifecycle (PENDING, then STATIC handed over or DYNAMIC).

Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from monoslam_shadow_node.common.core.feature_status import PENDING, STATIC
from monoslam_shadow_node.common.core.pose_links import cross_table
from monoslam_shadow_node.shadow_filter.core.rays import (
    THREE_RAY_DOF,
    View,
    pixel_ray_directions,
    ray_angle,
)
from monoslam_shadow_node.shadow_filter.core.shadow_classifier import (
    ClassifierConfig,
    Decision,
    due_test,
    predicted_visibility,
    score_tests,
)
from monoslam_shadow_node.shadow_filter.core.shadow_decision import decide, static_test
from monoslam_shadow_node.shadow_filter.core.shadow_ekf import (
    EkfConfig,
    EuclideanEstimate,
    initial_states,
    predict,
    static_hypothesis,
    update,
    world_estimates,
)
from monoslam_shadow_node.shadow_filter.core.shadow_track import Track
from monoslam_shadow_node.shadow_filter.core.static_fit import ROW_PRECISION, ROW_SIZE, view_rows
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.params import NON_NEGATIVE, check_fields, ruled

RESTART_AFTER_GATED = 3
"""Gated measurements in a row after which a feature's EKF restarts from its latest ray."""
_EYE = np.eye(3)


def _ray_precisions(to_pixel: FloatArray, pixel_sigma: float) -> FloatArray:
    """Return the pseudo-inverses (N, 3, 3) of sigma^2 A A' for A = d(direction)/d(pixel)
    (N, 3, 2) of full column rank."""
    gram = np.swapaxes(to_pixel, 1, 2) @ to_pixel  # (N, 2, 2)
    g00, g01, g11 = gram[:, 0, 0], gram[:, 0, 1], gram[:, 1, 1]
    determinant = g00 * g11 - g01 * g01
    inverse = np.empty_like(gram)
    inverse[:, 0, 0], inverse[:, 1, 1] = g11 / determinant, g00 / determinant
    inverse[:, 0, 1] = inverse[:, 1, 0] = -g01 / determinant
    root = to_pixel @ inverse  # A (A'A)^-1
    return np.asarray(root @ np.swapaxes(root, 1, 2) / pixel_sigma**2, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class _FrameViews:
    """One frame's rays: world directions (N, 3), covariances (N, 3, 3), d/dpixel (N, 3, 2)
    and ``static_fit.view_rows`` (N, ROW_SIZE)."""

    index: int
    frame: FrameInput
    directions: FloatArray
    covariances: FloatArray
    to_pixel: FloatArray
    constants: FloatArray
    pose_cross: dict[int, FloatArray]

    def view(self, k: int) -> View:
        """The ``View`` of ray k."""
        frame = self.frame
        return View(
            self.index, frame.stamp_ns, frame.centre, self.directions[k], self.covariances[k],
            frame.pose_covariance, self.to_pixel[k], self.pose_cross,
        )  # fmt: skip

    def precision(self, k: int) -> FloatArray:
        """The precision (3, 3) of ray k's direction."""
        return self.constants[k, ROW_PRECISION].reshape(3, 3)


class InputError(ValueError):
    """A frame the filter cannot use (the message names the culprit); the filter is unchanged."""


@dataclass(frozen=True)
class ShadowConfig:
    """Everything the Shadow filter needs besides the camera (``classify`` False: track only)."""

    ekf: EkfConfig = field(default_factory=EkfConfig)
    classifier: ClassifierConfig = field(default_factory=ClassifierConfig)
    max_missed_frames: int = ruled(5, range=NON_NEGATIVE)
    trajectory_length: int = ruled(100, range=NON_NEGATIVE)
    classify: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.classify, bool):
            raise ValueError(f'classify={self.classify!r}: must be true or false')
        check_fields(self)


@dataclass(frozen=True, eq=False)
class FrameInput:
    """One image's features, ``ids`` (M,) and raw ``pixels`` (M, 2), with the optical frame's
    pose: R_world_camera (3, 3), ``centre`` (3,) m, ``pose_covariance`` (6, 6) or None, and
    cross-covariances (K, 6, 6) with the poses at ``pose_cross_stamps`` (None: independent).
    """

    stamp_ns: int
    rotation: FloatArray
    centre: FloatArray
    ids: IntArray
    pixels: FloatArray
    pose_covariance: FloatArray | None = None
    pose_cross_stamps: tuple[int, ...] = ()
    pose_cross_covariances: FloatArray | None = None


@dataclass(eq=False)
class TrackReport:
    """One feature after a frame, world frame: position (3,) m, velocity (3,) m/s, their
    covariances (3, 3), test statistic (NaN: untested), decided_frame (-1: undecided),
    trajectory (K, 3) m."""

    id: int
    status: int
    position: FloatArray
    position_covariance: FloatArray
    velocity: FloatArray
    velocity_covariance: FloatArray
    test_statistic: float
    test_dof: int
    defined: bool
    first_frame: int
    decided_frame: int
    trajectory: FloatArray


@dataclass(frozen=True, eq=False)
class Handover:
    """A feature decided STATIC: world position (3,) m and covariance (3, 3)."""

    id: int
    stamp_ns: int
    position: FloatArray
    position_covariance: FloatArray
    frame: int
    parallax_rad: float


@dataclass(frozen=True, eq=False)
class FrameResult:
    """What one frame produced: tracks seen, handovers, decisions and warnings."""

    stamp_ns: int
    frame: int
    tracks: list[TrackReport]
    handovers: list[Handover]
    decisions: list[Decision]
    warnings: list[str]


class ShadowFilter:
    """The Shadow filter for one camera. Feed frames in stamp order with ``process``."""

    def __init__(self, camera: CameraModel, config: ShadowConfig | None = None) -> None:
        self.camera = camera
        self.config = config or ShadowConfig()
        self._tracks: list[Track] = []
        size = self.config.ekf.state_size
        self._states = np.zeros((0, size))
        self._covariances = np.zeros((0, size, size))
        self._released: set[int] = set()
        self._suspects: set[int] = set()
        self._strict = dataclasses.replace(self.config.classifier, unchecked_directions=0)
        self._static_test = static_test(self.config.classifier.static_test)
        ekf = self.config.ekf  # a static fit implausibly near a camera waits (near_static)
        self._prior = (ekf.initial_inverse_depth_per_m, ekf.initial_inverse_depth_sigma_per_m)
        self._frame = -1
        self._last: FrameInput | None = None
        self.linked_frames = 0  # frames whose pose came with a table (pose_links)

    @property
    def frame_count(self) -> int:
        """Frames processed so far."""
        return self._frame + 1

    @property
    def released_ids(self) -> frozenset[int]:
        """Ids handed over as STATIC (ignored from then on)."""
        return frozenset(self._released)

    @property
    def suspect_ids(self) -> frozenset[int]:
        """Ids SLAM revoked that have not been handed over again."""
        return frozenset(self._suspects)

    def revoke(self, ids: list[int]) -> list[int]:
        """Take back features SLAM revoked as suspects; return those this filter handed over."""
        taken = [int(i) for i in ids if int(i) in self._released]
        for feature_id in taken:
            self._released.discard(feature_id)
            self._suspects.add(feature_id)
        return taken

    def set_camera(self, camera: CameraModel) -> None:
        """Use new intrinsics from the next frame on (a camera_info change)."""
        self.camera = camera

    def process(self, frame: FrameInput) -> FrameResult:
        """Predict every held feature to this frame, update the observed ones, start new ones
        and classify. Raises InputError (filter unchanged) for a bad pose or stamp."""
        frame = self._validated(frame)
        warnings: list[str] = []
        finite = np.all(np.isfinite(frame.pixels), axis=1)
        if not np.all(finite):
            bad = ', '.join(str(int(i)) for i in frame.ids[~finite])
            warnings.append(f'ignored features with non-finite pixels: ids {bad}')
        ids, pixels = frame.ids[finite], frame.pixels[finite]
        self._frame += 1
        self.linked_frames += frame.pose_cross_covariances is not None
        if self._last is not None and len(self._tracks):
            self._predict(self._last, frame)
        row_of = {track.id: row for row, track in enumerate(self._tracks)}
        observed = [(k, row_of[int(i)]) for k, i in enumerate(ids) if int(i) in row_of]
        new = [
            k for k, i in enumerate(ids) if int(i) not in row_of and int(i) not in self._released
        ]
        # rays only for the features held or new (not for those handed over: SLAM's)
        kept = sorted([k for k, _ in observed] + new)
        if len(kept) < len(ids):
            position = {k: index for index, k in enumerate(kept)}
            observed = [(position[k], row) for k, row in observed]
            new = [position[k] for k in new]
            ids, pixels = ids[kept], pixels[kept]
        views = self._views(frame, pixels)
        seen_rows = set()
        if observed:
            columns = np.array([k for k, _ in observed])
            rows = np.array([row for _, row in observed])
            result = update(
                self._states[rows], self._covariances[rows], pixels[columns], self.camera,
                self.config.ekf,
            )  # fmt: skip
            self._states[rows], self._covariances[rows] = result.states, result.covariances
            restart: list[tuple[int, int]] = []
            for (k, row), used in zip(observed, result.used, strict=True):
                track = self._tracks[row]
                track.missed = 0
                seen_rows.add(row)
                track.gated = 0 if used else track.gated + 1
                if track.gated >= RESTART_AFTER_GATED:
                    warnings.append(
                        f'feature {track.id}: {track.gated} measurements in a row outside the '
                        'innovation gate; its filter restarts from this ray'
                    )
                    restart.append((k, row))
                    track.gated = 0
                elif not used:
                    warnings.append(f'feature {track.id}: measurement outside the innovation gate')
                if track.status == PENDING and self.config.classify:
                    track.add_view(views.view(k), views.precision(k), views.constants[k])
            if restart:
                again = [row for _, row in restart]
                self._states[again], self._covariances[again] = self._initial(
                    frame, [views.view(k) for k, _ in restart]
                )
        for row, track in enumerate(self._tracks):
            if row not in seen_rows:
                track.missed += 1
        if new:
            self._start(frame, ids[new], [views.view(k) for k in new], views.constants[new])
        decisions: list[Decision] = []
        estimate = world_estimates(self._states, self._covariances, frame.rotation, frame.centre)
        if self.config.classify:
            decisions = self._classify_pending(frame, warnings)
        reports, handovers = self._reports(frame, estimate)
        self._drop_finished()
        self._last = frame
        return FrameResult(frame.stamp_ns, self._frame, reports, handovers, decisions, warnings)

    # --- steps ------------------------------------------------------------------------------

    def _classify_pending(self, frame: FrameInput, warnings: list[str]) -> list[Decision]:
        """Classify the PENDING features seen in this frame; return the decisions."""
        # the static estimate of the features that can be classified in this frame
        candidates = [
            row
            for row, track in enumerate(self._tracks)
            if track.status == PENDING and track.missed == 0
        ]
        count = len(self._tracks)
        position, defined = np.zeros((count, 3)), np.zeros(count, dtype=bool)
        if candidates:
            static = world_estimates(
                *static_hypothesis(self._states[candidates], self._covariances[candidates]),
                frame.rotation,
                frame.centre,
            )
            position[candidates], defined[candidates] = static.position, static.defined
        visibility = predicted_visibility(self._tracks, position, defined)
        noise = self.config.ekf.tracking_noise
        dues = []
        for row, track in enumerate(self._tracks):
            if track.status == PENDING and track.missed == 0 and defined[row]:
                rule = self._strict if track.suspect else self.config.classifier
                seen = float(visibility[row, rule.unchecked_directions])
                due = due_test(track, position[row], seen, self._frame, rule, noise)
                if due is not None:
                    dues.append(due)
        # the frame's score tests together (shadow_decision.classify, one track at a time)
        decisions = []
        motions = score_tests(dues, noise)
        verdicts = self._static_test.verdicts(dues, motions, noise)
        for due, motion, verdict in zip(dues, motions, verdicts, strict=True):
            decision = decide(due, motion, self._frame, warnings, noise, verdict, self._prior)
            if decision is not None:
                decisions.append(decision)
        return decisions

    def _validated(self, frame: FrameInput) -> FrameInput:
        rotation = np.asarray(frame.rotation, dtype=np.float64)
        centre = np.asarray(frame.centre, dtype=np.float64)
        if rotation.shape != (3, 3) or not np.all(np.isfinite(rotation)):
            raise InputError('camera pose: the rotation is not a finite 3x3 matrix')
        # np.allclose(R'R, I, atol=1e-6) written out (it costs more than the rest of the checks)
        if not np.all(np.abs(rotation.T @ rotation - _EYE) <= 1e-6 + 1e-5 * _EYE):
            raise InputError('camera pose: the orientation is not a rotation (unnormalized?)')
        if centre.shape != (3,) or not np.all(np.isfinite(centre)):
            raise InputError('camera pose: the position is not 3 finite numbers')
        covariance = frame.pose_covariance
        if covariance is not None:
            covariance = np.asarray(covariance, dtype=np.float64)
            if covariance.shape != (6, 6) or not np.all(np.isfinite(covariance)):
                raise InputError('camera pose: the covariance is not a finite 6x6 matrix')
            if not np.any(covariance):
                covariance = None
        cross, cross_stamps = frame.pose_cross_covariances, tuple(frame.pose_cross_stamps)
        if cross is not None:
            cross = np.asarray(cross, dtype=np.float64)
            if cross.shape != (len(cross_stamps), 6, 6) or not np.all(np.isfinite(cross)):
                raise InputError(
                    'camera pose: the cross-covariances are not one finite 6x6 matrix per '
                    f'earlier stamp ({len(cross_stamps)} stamps, shape {cross.shape})'
                )
            if any(stamp >= frame.stamp_ns for stamp in cross_stamps):
                raise InputError('camera pose: a cross-covariance stamp is not earlier')
            if covariance is None or not len(cross_stamps):
                cross, cross_stamps = None, ()
        if self._last is not None and frame.stamp_ns <= self._last.stamp_ns:
            raise InputError(
                f'stamp {frame.stamp_ns} ns is not after the previous frame '
                f'({self._last.stamp_ns} ns): frames must come in stamp order'
            )
        ids = np.asarray(frame.ids, dtype=np.int64).reshape(-1)
        pixels = np.asarray(frame.pixels, dtype=np.float64).reshape(-1, 2)
        if len(ids) != len(pixels):
            raise InputError(f'{len(ids)} feature ids but {len(pixels)} pixel pairs')
        if len(set(ids.tolist())) != len(ids):
            raise InputError('feature ids repeat within one frame')
        return FrameInput(
            frame.stamp_ns, rotation, centre, ids, pixels, covariance, cross_stamps, cross
        )

    def _predict(self, previous: FrameInput, frame: FrameInput) -> None:
        rotation = frame.rotation.T @ previous.rotation
        translation = frame.rotation.T @ (previous.centre - frame.centre)
        dt = (frame.stamp_ns - previous.stamp_ns) * 1e-9
        self._states, self._covariances = predict(
            self._states, self._covariances, rotation, translation, dt, self.config.ekf
        )

    def _views(self, frame: FrameInput, pixels: FloatArray) -> _FrameViews:
        """Return the frame's views (``_FrameViews``)."""
        if not len(pixels):
            empty = np.zeros((0, 3))
            return _FrameViews(
                self._frame, frame, empty, np.zeros((0, 3, 3)), np.zeros((0, 3, 2)),
                np.zeros((0, ROW_SIZE)), {},
            )  # fmt: skip
        rays, jacobians = self.camera.pixel_rays(pixels)
        directions, covariances, to_pixel = pixel_ray_directions(
            rays, jacobians, frame.rotation, self.config.ekf.measurement_sigma_px
        )
        precisions = _ray_precisions(to_pixel, self.config.ekf.measurement_sigma_px)
        centres = np.broadcast_to(frame.centre, (len(directions), 3))
        constants = view_rows(centres, directions, covariances, precisions, frame.pose_covariance)
        table = cross_table(frame.pose_cross_stamps, frame.pose_cross_covariances)
        return _FrameViews(self._frame, frame, directions, covariances, to_pixel, constants, table)

    def _initial(self, frame: FrameInput, views: list[View]) -> tuple[FloatArray, FloatArray]:
        """EKF states and covariances of features first seen (or restarted) along views."""
        camera_directions = np.array([frame.rotation.T @ v.direction for v in views])
        camera_covariances = np.array(
            [frame.rotation.T @ v.direction_covariance @ frame.rotation for v in views]
        )
        jacobians = np.array(
            [frame.rotation.T @ v.pixel_jacobian for v in views if v.pixel_jacobian is not None]
        ).reshape(-1, 3, 2)
        return initial_states(camera_directions, camera_covariances, self.config.ekf, jacobians)

    def _start(
        self, frame: FrameInput, ids: IntArray, views: list[View], rows: FloatArray
    ) -> None:
        states, covariances = self._initial(frame, views)
        self._states = np.concatenate([self._states, states])
        self._covariances = np.concatenate([self._covariances, covariances])
        for track_id, view, row in zip(ids, views, rows, strict=True):
            track = Track(int(track_id), PENDING, self._frame, frame.stamp_ns)
            track.suspect = int(track_id) in self._suspects
            track.add_view(view, row[ROW_PRECISION].reshape(3, 3), row)
            self._tracks.append(track)

    def _reports(
        self, frame: FrameInput, estimate: EuclideanEstimate
    ) -> tuple[list[TrackReport], list[Handover]]:
        reports, handovers = [], []
        limit = self.config.trajectory_length
        for row, track in enumerate(self._tracks):
            if track.missed > 0:
                continue
            position = estimate.position[row]
            covariance = estimate.position_covariance[row]
            if track.status == STATIC and track.handover is not None:
                position, covariance = track.handover
                handovers.append(
                    Handover(
                        track.id, frame.stamp_ns, position, covariance, self._frame,
                        ray_angle(track.views[0].direction, track.views[-1].direction),
                    )
                )  # fmt: skip
            if limit and bool(estimate.defined[row]):
                track.trajectory.append(position, limit)
            reports.append(
                TrackReport(
                    track.id, track.status, position, covariance, estimate.velocity[row],
                    estimate.velocity_covariance[row], track.statistic,
                    THREE_RAY_DOF if math.isfinite(track.statistic) else 0,
                    bool(estimate.defined[row]), track.first_frame, track.decided_frame,
                    track.trajectory.array(limit),
                )
            )  # fmt: skip
        return reports, handovers

    def _drop_finished(self) -> None:
        """Release STATIC features and forget features not seen for too long."""
        keep = []
        for row, track in enumerate(self._tracks):
            if track.status == STATIC:
                self._released.add(track.id)
                self._suspects.discard(track.id)
            elif track.missed <= self.config.max_missed_frames:
                keep.append(row)
        if len(keep) != len(self._tracks):
            self._tracks = [self._tracks[row] for row in keep]
            self._states = self._states[keep]
            self._covariances = self._covariances[keep]
