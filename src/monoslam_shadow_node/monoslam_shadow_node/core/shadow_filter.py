"""The Shadow filter (paper 001, section III): one EKF per feature and the static/dynamic
classifier, with the feature lifecycle of the paper's Fig. 1.

Every new feature starts PENDING: the Shadow filter tracks it (``shadow_ekf``) and keeps its
views. Once the feature has been seen with enough parallax, two tests of the static
hypothesis decide (``ClassifierConfig``): the paper's three-ray test
(``rays.three_ray_test``) and the score test over all views (``static_fit``):

- either rejects: DYNAMIC. The feature stays in the Shadow filter and is tracked as it moves;
- both accept where the geometry could have seen motion: STATIC. It is handed over
  (``Handover``: the world position and covariance triangulated from all its views as a
  static point) and released; the SLAM filter owns it from then on, and its later sightings
  are ignored here.

Why two tests: three rays see motion that keeps them concurrent to first order (along the
viewing ray of a distant point, or parallel to a camera moving straight) only weakly, and in
the simulated room those are common; the all-view test sees it as soon as the camera path
bends or the depth changes. The three-ray test stays as the paper's classifier; the second
test only adds rejections, and both share alpha.

Minimum-parallax rule: test j waits until the first and the current ray are at least
``min_parallax_rad * parallax_growth**j`` apart as seen from the feature's position
estimated as if it were static (the EKF conditioned on zero velocity; its depth must be
known: w above 3 sigma), the camera has moved ``min_baseline_m``, and some earlier camera
centre lies between the first and the current one (at least ``middle_min_fraction`` of their
distance from both); until then nothing is decided.

Camera poses come from outside (the SLAM filter, or ground truth in the paper's Fig. 3
experiment) with their covariance; the filter assumes them independent between frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import brentq
from scipy.stats import ncx2

from monoslam_shadow_node.core.projective import FloatArray, chi2_quantile
from monoslam_shadow_node.core.rays import (
    THREE_RAY_DOF,
    View,
    pixel_ray_directions,
    ray_angle,
    three_ray_test,
)
from monoslam_shadow_node.core.shadow_ekf import (
    STATE_SIZE,
    EkfConfig,
    EuclideanEstimate,
    initial_states,
    predict,
    static_hypothesis,
    update,
    world_estimates,
)
from monoslam_shadow_node.core.static_fit import MOTION_DOF, motion_score_test
from slam_core.camera import CameraModel

PENDING, STATIC, DYNAMIC = 0, 1, 2
TEST_DELAY_FRAMES = 1
"""A test triggered in frame k uses the view of frame k + 1 as its last ray, whose noise did
not take part in the trigger (the EKF estimate just updated with frame k's ray)."""
RESTART_AFTER_GATED = 3
"""A feature whose measurements fall outside the innovation gate this many frames in a row
has lost its track (it moved faster or turned harder than the process noise allows): its EKF
restarts from the latest ray, keeping its id, status and views."""
STATUS_NAMES = {PENDING: 'PENDING', STATIC: 'STATIC', DYNAMIC: 'DYNAMIC'}
IntArray = NDArray[np.int64]


class InputError(ValueError):
    """A frame the filter cannot use (the message names the culprit); the filter is unchanged."""


@dataclass(frozen=True)
class ClassifierConfig:
    """The static/dynamic decision (units in the names).

    Test j waits for a parallax of ``min_parallax_rad * parallax_growth**j``, and runs two
    tests of the static hypothesis, each at ``test_alpha`` = alpha / (2 max_tests)
    (Bonferroni over everything a feature may get, so a static feature is called dynamic with
    probability at most ``alpha``): the paper's three-ray test and the score test over all
    views (``static_fit``). Either rejecting makes the feature DYNAMIC. Both accepting makes
    it STATIC once the geometry could have seen motion: a feature moving at
    ``min_detectable_speed_m_s`` along any principal direction of motion except the
    ``unchecked_directions`` least visible ones would have been rejected by the score test with
    probability ``detection_power``; otherwise it waits for the next test. With
    ``unchecked_directions`` = 0 that holds for every direction (a guarantee that can take
    long: motion along the viewing ray of a distant point, or parallel to a camera moving
    straight, shows only at second order in time); 1 (the default) leaves the least visible
    direction unchecked. After ``max_tests`` tests without a decision the feature stays
    PENDING.
    """

    alpha: float = 0.05
    min_parallax_rad: float = math.radians(2.0)
    parallax_growth: float = 1.5
    max_tests: int = 6
    min_baseline_m: float = 0.05
    middle_min_fraction: float = 0.25
    min_detectable_speed_m_s: float = 0.3
    detection_power: float = 0.99
    unchecked_directions: int = 1

    def __post_init__(self) -> None:
        checks = (
            ('alpha', self.alpha, 0 < self.alpha < 1, 'must be in (0, 1)'),
            ('min_parallax_rad', self.min_parallax_rad, 0 < self.min_parallax_rad < math.pi,
             'must be in (0, pi) rad'),
            ('parallax_growth', self.parallax_growth, self.parallax_growth >= 1, 'must be >= 1'),
            ('max_tests', self.max_tests,
             isinstance(self.max_tests, int) and self.max_tests >= 1, 'must be an integer >= 1'),
            ('min_baseline_m', self.min_baseline_m, self.min_baseline_m > 0, 'must be > 0 m'),
            ('middle_min_fraction', self.middle_min_fraction,
             0 < self.middle_min_fraction <= 0.5, 'must be in (0, 0.5]'),
            ('min_detectable_speed_m_s', self.min_detectable_speed_m_s,
             self.min_detectable_speed_m_s >= 0, 'must be >= 0 m/s'),
            ('detection_power', self.detection_power, 0 < self.detection_power < 1,
             'must be in (0, 1)'),
            ('unchecked_directions', self.unchecked_directions,
             self.unchecked_directions in (0, 1, 2), 'must be 0, 1 or 2'),
        )  # fmt: skip
        for name, value, ok, rule in checks:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f'{name}={value!r}: must be a number')
            if not math.isfinite(value) or not ok:
                raise ValueError(f'{name}={value!r}: {rule}')

    @property
    def test_alpha(self) -> float:
        """The level of each test (alpha split over both tests of every round, Bonferroni)."""
        return self.alpha / (2 * self.max_tests)

    def parallax_for_test(self, index: int) -> float:
        """Return the parallax (rad) test ``index`` (0-based) waits for."""
        return float(self.min_parallax_rad * self.parallax_growth**index)

    @property
    def required_noncentrality(self) -> float:
        """The noncentrality at which the score test at ``test_alpha`` rejects with
        probability ``detection_power``."""
        return _required_noncentrality(self.test_alpha, self.detection_power)


@lru_cache(maxsize=32)
def _required_noncentrality(alpha: float, power: float) -> float:
    threshold = chi2_quantile(1.0 - alpha, MOTION_DOF)

    def shortfall(noncentrality: float) -> float:
        return float(ncx2.sf(threshold, MOTION_DOF, noncentrality)) - power

    return float(brentq(shortfall, 1e-6, 1e4))


@dataclass(frozen=True)
class ShadowConfig:
    """Everything the Shadow filter needs besides the camera. ``classify`` False makes it a
    bearing-only tracker alone: every feature stays PENDING in its EKF for as long as it is
    tracked (the paper's Fig. 3 experiment; the consistency evaluation uses it, because
    handing features over would select which estimates remain)."""

    ekf: EkfConfig = field(default_factory=EkfConfig)
    classifier: ClassifierConfig = field(default_factory=ClassifierConfig)
    max_missed_frames: int = 5
    trajectory_length: int = 100
    classify: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.classify, bool):
            raise ValueError(f'classify={self.classify!r}: must be true or false')
        for name in ('max_missed_frames', 'trajectory_length'):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f'{name}={value!r}: must be an integer >= 0')


@dataclass(frozen=True, eq=False)
class FrameInput:
    """One image's features with the camera pose at its stamp.

    ``rotation`` (3, 3) is R_world_camera of the optical frame, ``centre`` (3,) m its
    position, ``pose_covariance`` (6, 6) over (position, rotation about the world axes) or
    None (known pose); ``ids`` (M,) track ids and ``pixels`` (M, 2) raw-image pixels.
    """

    stamp_ns: int
    rotation: FloatArray
    centre: FloatArray
    ids: IntArray
    pixels: FloatArray
    pose_covariance: FloatArray | None = None


@dataclass(frozen=True, eq=False)
class TrackReport:
    """One feature after a frame, world frame: status, position (3,) m and covariance (3, 3),
    velocity (3,) m/s and covariance (3, 3), the latest test statistic (NaN before any test)
    with its degrees of freedom, whether the position is defined (depth known), the frame of
    first sight and of the decision (-1: undecided), and recent positions (K, 3)."""

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
    """A feature decided STATIC: its world position (3,) m and covariance (3, 3), conditioned
    on zero velocity, the camera frame it was decided in and the parallax (rad) of the last
    test."""

    id: int
    stamp_ns: int
    position: FloatArray
    position_covariance: FloatArray
    frame: int
    parallax_rad: float


@dataclass(frozen=True, eq=False)
class Decision:
    """A classification made in a frame (for evaluation): the feature, its new status, the
    frames since first sight and the parallax (rad) and baseline (m) of the deciding test."""

    id: int
    status: int
    frames_since_first: int
    parallax_rad: float
    baseline_m: float
    statistic: float


@dataclass(frozen=True, eq=False)
class FrameResult:
    """What one frame produced: the tracks held (PENDING and DYNAMIC, and STATIC ones in the
    frame they were handed over), the handovers, the decisions and warnings."""

    stamp_ns: int
    frame: int
    tracks: list[TrackReport]
    handovers: list[Handover]
    decisions: list[Decision]
    warnings: list[str]


@dataclass
class _Track:
    id: int
    status: int
    first_frame: int
    first_stamp_ns: int
    views: list[View] = field(default_factory=list)
    # per view: camera centre (N, 3), direction (N, 3), its precision (N, 3, 3) (the
    # pseudo-inverse of its covariance) and time since first sight (N,) s, for
    # ShadowFilter._predicted_visibility
    centres: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    directions: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    precisions: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    taus: FloatArray = field(default_factory=lambda: np.zeros(0))
    tests_run: int = 0
    scheduled_frame: int = -1
    statistic: float = math.nan
    decided_frame: int = -1
    missed: int = 0
    gated: int = 0
    handover: tuple[FloatArray, FloatArray] | None = None
    visibility_wait: float = 0.0
    predicted_visible: float = 0.0
    milestone_due: bool = False

    def add_view(self, view: View, precision: FloatArray) -> None:
        """Keep a view (and its arrays for the visibility prediction)."""
        self.views.append(view)
        self.centres = np.vstack([self.centres, view.centre])
        self.directions = np.vstack([self.directions, view.direction])
        self.precisions = np.concatenate([self.precisions, precision[None]])
        self.taus = np.append(self.taus, (view.stamp_ns - self.first_stamp_ns) * 1e-9)

    trajectory: list[FloatArray] = field(default_factory=list)


class ShadowFilter:
    """The Shadow filter for one camera. Feed frames in stamp order with ``process``."""

    def __init__(self, camera: CameraModel, config: ShadowConfig | None = None) -> None:
        self.camera = camera
        self.config = config or ShadowConfig()
        self._tracks: list[_Track] = []
        self._states = np.zeros((0, STATE_SIZE))
        self._covariances = np.zeros((0, STATE_SIZE, STATE_SIZE))
        self._released: set[int] = set()
        self._frame = -1
        self._last: FrameInput | None = None

    @property
    def frame_count(self) -> int:
        """Frames processed so far."""
        return self._frame + 1

    @property
    def released_ids(self) -> frozenset[int]:
        """Ids handed over as STATIC (ignored from then on)."""
        return frozenset(self._released)

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
        if self._last is not None and len(self._tracks):
            self._predict(self._last, frame)
        row_of = {track.id: row for row, track in enumerate(self._tracks)}
        observed = [(k, row_of[int(i)]) for k, i in enumerate(ids) if int(i) in row_of]
        new = [
            k for k, i in enumerate(ids) if int(i) not in row_of and int(i) not in self._released
        ]
        views, precisions = self._views(frame, pixels)
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
                    track.add_view(views[k], precisions[k])
            if restart:
                again = [row for _, row in restart]
                self._states[again], self._covariances[again] = self._initial(
                    frame, [views[k] for k, _ in restart]
                )
        for row, track in enumerate(self._tracks):
            if row not in seen_rows:
                track.missed += 1
        if new:
            self._start(frame, ids[new], [views[k] for k in new], precisions[new])
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
        """Classify every PENDING feature observed in this frame whose static estimate is
        defined (``_classify``); return the decisions."""
        static = world_estimates(
            *static_hypothesis(self._states, self._covariances), frame.rotation, frame.centre
        )
        visibility = self._predicted_visibility(static.position, static.defined, frame.centre)
        decisions = []
        for row, track in enumerate(self._tracks):
            if track.status == PENDING and track.missed == 0 and static.defined[row]:
                decision = self._classify(track, static.position[row], visibility[row], warnings)
                if decision is not None:
                    decisions.append(decision)
        return decisions

    def _validated(self, frame: FrameInput) -> FrameInput:
        rotation = np.asarray(frame.rotation, dtype=np.float64)
        centre = np.asarray(frame.centre, dtype=np.float64)
        if rotation.shape != (3, 3) or not np.all(np.isfinite(rotation)):
            raise InputError('camera pose: the rotation is not a finite 3x3 matrix')
        if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6):
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
        if self._last is not None and frame.stamp_ns <= self._last.stamp_ns:
            raise InputError(
                f'stamp {frame.stamp_ns} ns is not after the previous frame '
                f'({self._last.stamp_ns} ns): frames must come in stamp order'
            )
        ids = np.asarray(frame.ids, dtype=np.int64).reshape(-1)
        pixels = np.asarray(frame.pixels, dtype=np.float64).reshape(-1, 2)
        if len(ids) != len(pixels):
            raise InputError(f'{len(ids)} feature ids but {len(pixels)} pixel pairs')
        if len(np.unique(ids)) != len(ids):
            raise InputError('feature ids repeat within one frame')
        return FrameInput(frame.stamp_ns, rotation, centre, ids, pixels, covariance)

    def _predict(self, previous: FrameInput, frame: FrameInput) -> None:
        rotation = frame.rotation.T @ previous.rotation
        translation = frame.rotation.T @ (previous.centre - frame.centre)
        dt = (frame.stamp_ns - previous.stamp_ns) * 1e-9
        self._states, self._covariances = predict(
            self._states, self._covariances, rotation, translation, dt, self.config.ekf
        )

    def _views(self, frame: FrameInput, pixels: FloatArray) -> tuple[list[View], FloatArray]:
        """Return the frame's views and their ray precisions (N, 3, 3): the pseudo-inverse
        of each direction's covariance (rank 2, pixel noise only)."""
        if not len(pixels):
            return [], np.zeros((0, 3, 3))
        rays, jacobians = self.camera.pixel_rays(pixels)
        directions, covariances = pixel_ray_directions(
            rays, jacobians, frame.rotation, self.config.ekf.pixel_sigma_px
        )
        views = [
            View(self._frame, frame.stamp_ns, frame.centre, d, c, frame.pose_covariance)
            for d, c in zip(directions, covariances, strict=True)
        ]
        precisions = np.linalg.pinv(covariances, rcond=1e-9, hermitian=True)
        return views, np.asarray(precisions, dtype=np.float64)

    def _initial(self, frame: FrameInput, views: list[View]) -> tuple[FloatArray, FloatArray]:
        """EKF states and covariances of features first seen (or restarted) along views."""
        camera_directions = np.array([frame.rotation.T @ v.direction for v in views])
        camera_covariances = np.array(
            [frame.rotation.T @ v.direction_covariance @ frame.rotation for v in views]
        )
        return initial_states(camera_directions, camera_covariances, self.config.ekf)

    def _start(
        self, frame: FrameInput, ids: IntArray, views: list[View], precisions: FloatArray
    ) -> None:
        states, covariances = self._initial(frame, views)
        self._states = np.concatenate([self._states, states])
        self._covariances = np.concatenate([self._covariances, covariances])
        for track_id, view, precision in zip(ids, views, precisions, strict=True):
            track = _Track(int(track_id), PENDING, self._frame, frame.stamp_ns)
            track.add_view(view, precision)
            self._tracks.append(track)

    def _predicted_visibility(
        self, positions: FloatArray, defined: NDArray[np.bool_], centre: FloatArray
    ) -> FloatArray:
        """Return, per held feature, the score test's noncentrality per (m/s)^2 along the
        direction ``unchecked_directions`` from the least visible (0 where not computed).

        This is ``static_fit``'s S evaluated at the feature's static EKF estimate instead of
        the fitted point, without the pose covariance and the small r d' term of the
        Jacobian: J_i' W_i J_i = M_i / rho_i^2 with M_i the direction's precision and
        rho_i = d_i' (P - C_i) its depth. It only says when to test (the decision uses the
        exact S). Only features past the minimum parallax are evaluated; the per-view
        depths matter (with one depth for all views, motion parallel to the camera path
        would look visible when it is not)."""
        result = np.zeros(len(self._tracks))
        index = self.config.classifier.unchecked_directions
        for row, track in enumerate(self._tracks):
            if not (track.status == PENDING and track.missed == 0 and defined[row]):
                continue
            if track.scheduled_frame >= 0 or len(track.taus) < 3:
                continue
            offset = positions[row] - track.centres
            depth = np.einsum('ni,ni->n', track.directions, offset)
            if np.any(depth <= 0.0):
                continue
            weighted = track.precisions / (depth**2)[:, None, None]
            tau = track.taus - track.taus.mean()
            a0 = weighted.sum(axis=0)
            a1 = np.einsum('n,nij->ij', tau, weighted)
            a2 = np.einsum('n,nij->ij', tau * tau, weighted)
            try:
                schur = a2 - a1 @ np.linalg.solve(a0, a1)
            except np.linalg.LinAlgError:
                continue
            values = np.linalg.eigvalsh(0.5 * (schur + schur.T))
            result[row] = max(float(values[index]), 0.0)
        return result

    def _classify(
        self, track: _Track, position: FloatArray, visibility: float, warnings: list[str]
    ) -> Decision | None:
        """Run the next pair of tests once the geometry allows it: at the next parallax
        milestone, or as soon as the predicted visibility of motion suffices for a decision.

        When to test and which middle view to use are decided from the camera centres and the
        EKF's position estimate, never from the three measured rays themselves: choosing the
        rays by their own noisy directions (the first frame whose ray is far enough from the
        first, the view farthest from both ends) biases T upwards (measured: 7 % rejections
        of static features at a 2.5 % level).
        """
        settings = self.config.classifier
        if track.tests_run >= settings.max_tests:
            return None
        first, last = track.views[0], track.views[-1]
        baseline = float(np.linalg.norm(last.centre - first.centre))
        speed = settings.min_detectable_speed_m_s
        if track.scheduled_frame < 0:
            if baseline < settings.min_baseline_m:
                return None
            parallax = ray_angle(_unit(position - first.centre), _unit(position - last.centre))
            visible = visibility * speed**2
            track.milestone_due = parallax >= settings.parallax_for_test(track.tests_run)
            if track.milestone_due or (
                speed > 0
                and parallax >= settings.min_parallax_rad
                and visible >= settings.required_noncentrality
                and visible >= track.visibility_wait
            ):
                track.scheduled_frame = self._frame + TEST_DELAY_FRAMES
                track.predicted_visible = visible
            return None
        if self._frame < track.scheduled_frame:
            return None
        track.scheduled_frame = -1
        parallax = ray_angle(_unit(position - first.centre), _unit(position - last.centre))
        middle = _middle_view(track.views, settings.middle_min_fraction * baseline)
        if middle is None:
            return None
        level = settings.test_alpha
        motion = motion_score_test(track.views, level, position)
        if motion is None:
            warnings.append(f'feature {track.id}: its views do not fix a static point yet')
            return None
        # Whether a decision is possible is geometry (S), not the test's outcome: when it
        # is not and no parallax milestone is due, nothing is tested and no alpha is spent.
        decisive = speed == 0 or (
            motion.visibility[settings.unchecked_directions] * speed**2
            >= settings.required_noncentrality
        )
        if not decisive:
            # the prediction was optimistic: ask it for half as much again before retrying
            track.visibility_wait = 1.5 * track.predicted_visible
            if not track.milestone_due:
                return None
        try:
            test = three_ray_test(first, middle, last, level)
        except ValueError as error:
            warnings.append(f'feature {track.id}: test skipped, degenerate geometry ({error})')
            return None
        track.statistic = test.result.statistic
        track.tests_run += 1
        frames = self._frame - track.first_frame
        if test.result.rejected or motion.result.rejected:
            track.status, track.decided_frame = DYNAMIC, self._frame
            track.views = []
            return Decision(track.id, DYNAMIC, frames, parallax, baseline, track.statistic)
        if not decisive:
            return None  # accepted, but motion could have gone unseen: wait for more views
        track.status, track.decided_frame = STATIC, self._frame
        track.handover = (motion.point, motion.covariance)
        return Decision(track.id, STATIC, frames, parallax, baseline, track.statistic)

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
                track.trajectory.append(position)
                del track.trajectory[:-limit]
            reports.append(
                TrackReport(
                    track.id, track.status, position, covariance, estimate.velocity[row],
                    estimate.velocity_covariance[row], track.statistic,
                    THREE_RAY_DOF if math.isfinite(track.statistic) else 0,
                    bool(estimate.defined[row]), track.first_frame, track.decided_frame,
                    np.array(track.trajectory).reshape(-1, 3),
                )
            )  # fmt: skip
        return reports, handovers

    def _drop_finished(self) -> None:
        """Release STATIC features and forget features not seen for too long."""
        keep = []
        for row, track in enumerate(self._tracks):
            if track.status == STATIC:
                self._released.add(track.id)
            elif track.missed <= self.config.max_missed_frames:
                keep.append(row)
        if len(keep) != len(self._tracks):
            self._tracks = [self._tracks[row] for row in keep]
            self._states = self._states[keep]
            self._covariances = self._covariances[keep]


def _middle_view(views: list[View], min_distance_m: float) -> View | None:
    """Return the view between the first and the last whose camera centre is farthest from
    both ends' centres, if at least ``min_distance_m`` from each; else None."""
    if len(views) < 3:
        return None
    centres = np.array([view.centre for view in views[1:-1]])
    distance = np.minimum(
        np.linalg.norm(centres - views[0].centre, axis=1),
        np.linalg.norm(centres - views[-1].centre, axis=1),
    )
    best = int(np.argmax(distance))
    return views[1 + best] if distance[best] >= min_distance_m else None


def _unit(vector: FloatArray) -> FloatArray:
    norm = float(np.linalg.norm(vector))
    return vector / norm if norm > 0 else vector
