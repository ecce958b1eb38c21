"""EM-SAM online: an incremental smoother with the EM weights updated where a change lands.

The smoother is GTSAM's iSAM2 (a Bayes tree: a new keyframe relinearizes and re-solves
only the cliques its factors touch). Poses are ``Pose2`` (key: the keyframe's index),
landmarks ``Point2`` (key: symbol 'l' and the landmark id). A differential-drive increment
(paper 000, eq. 2) enters as the SE(2) relative pose it gives, exact for the mean, with its
first-order covariance (``between_of_increment``); a sighting as a bearing-range factor.

The EM weights (``core.em_weights``, the robust mode's per-landmark test) are updated online
for the landmarks a keyframe sees: their sightings' squared Mahalanobis innovations at the
smoother's estimate (with the test's model error; the sensor model as given, without the
batch's variance factors), the per-sighting gate, and the M-step. A landmark
whose weight moved by more than ``weight_step`` has all its sightings' factors replaced with
the new row scale (information times w, as the E-step's sqrt(w) row scale), one whose gate
changed those sightings' factors; the test repeats within the keyframe until no weight
moves. Landmarks below ``moveable_threshold`` are the moveable set.

Rows the batch scales to the floor (gated sightings; every sighting of a landmark whose
weight is at the floor) carry no factor here: their pull is nil, and GTSAM's factorization
does not take rows a million times weaker than their neighbours reliably. A landmark left
without factors is parked (a prior holds its variable) and placed by its own least squares
while it is. A new sighting of a mapped landmark is gated before it enters, with the
landmark's gate at the estimate with it added, and a sighting whose bearing innovation
exceeds a right angle is held out until the estimate brings it within one (the bearing's
linearization points no way toward it): a gross outlier never carries full weight into an
update, because one step of the smoother with it cannot be taken back by removing it.

The full pass (``core.em.run_em`` over everything collected) stays the batch answer; this
smoother does not take its result.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.em_weights import (
    ROW_SCALE_FLOOR,
    chi2_quantile,
    covariances_for_test,
    gate_outliers,
    m_step,
    squared_mahalanobis,
)
from em_sam_node.core.factors import range_bearing_error, range_bearing_error_jacobians
from em_sam_node.core.problem import FloatArray
from em_sam_node.core.sightings import sighting_jacobians
from slam_core.geometry.se2 import range_bearing_to_point


def between_of_increment(u: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return the SE(2) relative poses (M, 3) of differential-drive increments u (M, 3)
    (eq. 2: exact for the mean) and their first-order covariances (M, 3, 3)."""
    u = np.asarray(u, dtype=np.float64).reshape(-1, 3)
    half = u[:, 2] / 2.0
    c, s = np.cos(half), np.sin(half)
    between = np.column_stack([c * u[:, 0] - s * u[:, 1], s * u[:, 0] + c * u[:, 1], u[:, 2]])
    jacobian = np.zeros((len(u), 3, 3))
    jacobian[:, 0, 0], jacobian[:, 0, 1] = c, -s
    jacobian[:, 1, 0], jacobian[:, 1, 1] = s, c
    jacobian[:, 0, 2] = -0.5 * between[:, 1]
    jacobian[:, 1, 2] = 0.5 * between[:, 0]
    jacobian[:, 2, 2] = 1.0
    covariance: FloatArray = jacobian @ np.asarray(cov, np.float64) @ np.swapaxes(jacobian, 1, 2)
    return between, covariance


def load_gtsam() -> Any:
    """Import GTSAM (a dependency of the online mapper); a clear error if it is missing."""
    try:
        import gtsam
    except ImportError as err:  # pragma: no cover - the bootstrap installs it
        raise ImportError(
            'EM-SAM online needs GTSAM (pip install gtsam==4.3.0; scripts/bootstrap.sh '
            'installs it)'
        ) from err
    return gtsam


@dataclass(frozen=True)
class IncrementalConfig:
    """The smoother's settings: iSAM2's relinearization (a variable is relinearized when
    its update exceeds ``relinearize_threshold``, checked every ``relinearize_skip``
    updates; GTSAM's defaults) and the weight change that replaces a landmark's factors."""

    relinearize_threshold: float = 0.1
    relinearize_skip: int = 10
    weight_step: float = 0.05

    def __post_init__(self) -> None:
        if not (np.isfinite(self.relinearize_threshold) and self.relinearize_threshold > 0):
            raise ValueError(f'relinearize_threshold={self.relinearize_threshold!r}: must be > 0')
        if self.relinearize_skip < 1:
            raise ValueError(f'relinearize_skip={self.relinearize_skip!r}: must be >= 1')
        if not 0 < self.weight_step < 1:
            raise ValueError(f'weight_step={self.weight_step!r}: must be in (0, 1)')


PARKING_SIGMA_M = 1.0  # the parking prior's standard deviation
PARKED_ITERATIONS = 10  # Gauss-Newton steps placing a parked landmark


@dataclass
class _Landmark:
    """A landmark's sightings: keyframe index, (range, bearing), covariance, the index of
    its factor in the smoother (-1 while it has none) and its gate; the weight its factors
    carry; while none does, the index of the prior that parks it and its own estimate."""

    poses: list[int] = field(default_factory=list)
    z: list[FloatArray] = field(default_factory=list)
    cov: list[FloatArray] = field(default_factory=list)
    factors: list[int] = field(default_factory=list)
    gated: list[bool] = field(default_factory=list)
    held: list[bool] = field(default_factory=list)  # beyond linearization at the last test
    weight: float = 1.0
    applied: float = 1.0  # the weight its factors carry
    parked: int = -1  # the parking prior's factor, -1 when it has sightings in the smoother
    position: FloatArray | None = None  # its own estimate while parked

    def carries(self, k: int) -> bool:
        """Whether sighting k belongs in the smoother: not gated, and the landmark's weight
        above the floor (below it the E-step's row scale is the floor, whose pull on the
        poses is nil; GTSAM's factorization does not take such rows reliably)."""
        return not (self.gated[k] or self.held[k]) and np.sqrt(self.applied) > ROW_SCALE_FLOOR


@dataclass(frozen=True)
class _NewSighting:
    """A sighting about to enter: its keyframe, that keyframe's pose (a gtsam Pose2), the
    increment (relative Pose2, covariance (3, 3)) that placed it if it is the new keyframe
    (else None), (range m, bearing rad) and covariance (2, 2)."""

    keyframe: int
    pose: Any
    increment: tuple[Any, FloatArray] | None
    z: FloatArray
    cov: FloatArray


@dataclass(frozen=True)
class UpdateStats:
    """One keyframe's update: its wall time (s), the landmarks it saw, those whose factors
    were replaced for a new weight, and the moveable set after it."""

    seconds: float
    seen: tuple[int, ...]
    reweighted: tuple[int, ...]
    moveable: frozenset[int]


class IncrementalEmSam:
    """The online smoother (module docstring). Keyframes come in order, one per call."""

    def __init__(
        self,
        config: EmConfig,
        prior_pose: FloatArray,
        prior_cov: FloatArray,
        incremental: IncrementalConfig | None = None,
    ) -> None:
        self.gtsam = load_gtsam()
        self.config = config
        self.incremental = incremental or IncrementalConfig()
        self.prior_pose = np.asarray(prior_pose, np.float64).reshape(3)
        self.prior_cov = np.asarray(prior_cov, np.float64).reshape(3, 3)
        self.landmarks: dict[int, _Landmark] = {}
        self.num_keyframes = 0
        self._pending_removals: list[int] = []
        self._pending: list[tuple[int, int]] = []  # (landmark id, sighting) to (re)add
        params = self.gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.incremental.relinearize_threshold)
        params.relinearizeSkip = self.incremental.relinearize_skip
        # check only the cliques an update touched for relinearization, not every variable:
        # per-update cost independent of the run's length
        params.enablePartialRelinearizationCheck = True
        self.solver = self.gtsam.ISAM2(params)

    # --- keyframes ----------------------------------------------------------------------

    def add_keyframe(
        self,
        odometry: tuple[FloatArray, FloatArray] | None,
        sightings: Sequence[tuple[int, FloatArray, FloatArray]],
        late: Sequence[tuple[int, int, FloatArray, FloatArray]] = (),
    ) -> UpdateStats:
        """Add the next keyframe: its increment from the one before ((u (3,), cov (3, 3)),
        None for the first keyframe, which takes the prior) and its sightings (landmark id,
        (range m, bearing rad), covariance (2, 2)), with ``late`` sightings of earlier
        keyframes (keyframe index first); update the smoother and the weights of the
        landmarks they saw."""
        started = time.perf_counter()
        gtsam = self.gtsam
        index = self.num_keyframes
        if (odometry is None) != (index == 0):
            raise ValueError('the first keyframe takes the prior, every later one an increment')
        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if odometry is None:
            start = gtsam.Pose2(*self.prior_pose)
            factors.add(
                gtsam.PriorFactorPose2(
                    0, start, gtsam.noiseModel.Gaussian.Covariance(self.prior_cov)
                )
            )
        else:
            between, covariance = between_of_increment(odometry[0], odometry[1][None])
            relative = gtsam.Pose2(*between[0])
            start = self._pose(index - 1).compose(relative)
            factors.add(
                gtsam.BetweenFactorPose2(
                    index - 1, index, relative, gtsam.noiseModel.Gaussian.Covariance(covariance[0])
                )
            )
        values.insert(index, start)
        sighted: set[int] = set()
        created: set[int] = set()
        for keyframe, landmark_id, z, cov in [*late, *((index, *s) for s in sightings)]:
            if not 0 <= keyframe <= index:
                raise ValueError(f'a sighting of keyframe {keyframe}: there are {index + 1}')
            landmark_id = int(landmark_id)
            landmark = self.landmarks.get(landmark_id)
            z = np.asarray(z, np.float64).reshape(2)
            cov = np.asarray(cov, np.float64).reshape(2, 2)
            seen_from = start if keyframe == index else self._pose(keyframe)
            increment = (relative, covariance[0]) if keyframe == index and index > 0 else None
            gated, held = (
                self._enter(landmark_id, _NewSighting(keyframe, seen_from, increment, z, cov))
                if landmark and landmark_id not in created
                else (False, False)  # a landmark this keyframe maps is not in the smoother yet
            )
            if landmark is None:
                created.add(landmark_id)
                landmark = self.landmarks[landmark_id] = _Landmark()
                point = seen_from.transformFrom(
                    gtsam.Point2(z[0] * np.cos(z[1]), z[0] * np.sin(z[1]))
                )
                values.insert(gtsam.symbol('l', landmark_id), point)
            landmark.poses.append(int(keyframe))
            landmark.z.append(z)
            landmark.cov.append(cov)
            landmark.factors.append(-1)
            landmark.gated.append(gated)
            landmark.held.append(held)
            if landmark.carries(len(landmark.poses) - 1):
                self._pending.append((landmark_id, len(landmark.poses) - 1))
            sighted.add(landmark_id)
        self.num_keyframes += 1
        self._update(factors, values)
        seen = tuple(sorted(sighted))
        reweighted: set[int] = set()
        for _ in range(self.config.max_iterations):  # EM on the landmarks the keyframe saw
            changed = self._update_weights(seen)
            if not changed:
                break
            reweighted.update(changed)
            self._update(gtsam.NonlinearFactorGraph(), gtsam.Values())
        return UpdateStats(
            time.perf_counter() - started, seen, tuple(sorted(reweighted)), self.moveable
        )

    def _update(self, factors: Any, values: Any) -> None:
        """One smoother update: ``factors`` and ``values``, and the queued sighting factors
        (k >= 0), parking priors (k = -1) and removals."""
        queued, self._pending = self._pending, []
        for landmark_id, k in queued:
            factors.add(
                self._sighting_factor(landmark_id, k) if k >= 0 else self._parking(landmark_id)
            )
        removals, self._pending_removals = self._pending_removals, []
        result = self.solver.update(factors, values, removals)
        new_indices = list(result.getNewFactorsIndices())  # in the order they were added
        for (landmark_id, k), factor in zip(
            queued, new_indices[len(new_indices) - len(queued) :], strict=True
        ):
            landmark = self.landmarks[landmark_id]
            if k >= 0:
                landmark.factors[k] = int(factor)
            else:
                landmark.parked = int(factor)

    def _pose(self, index: int) -> Any:
        return self.solver.calculateEstimatePose2(index)

    def _sighting_factor(self, landmark_id: int, k: int) -> Any:
        gtsam = self.gtsam
        landmark = self.landmarks[landmark_id]
        cov = landmark.cov[k][np.ix_([1, 0], [1, 0])] / landmark.applied  # (bearing, range)
        z = landmark.z[k]
        return gtsam.BearingRangeFactor2D(
            landmark.poses[k],
            gtsam.symbol('l', landmark_id),
            gtsam.Rot2(float(z[1])),
            float(z[0]),
            gtsam.noiseModel.Gaussian.Covariance(cov),
        )

    def _parking(self, landmark_id: int) -> Any:
        """A prior that holds a landmark without sightings in the smoother where it is. It
        pulls nothing (the landmark has no other factor); a weak one would put a pivot out
        of the factorization's range (GTSAM reports such a clique as indeterminate)."""
        gtsam = self.gtsam
        symbol = gtsam.symbol('l', landmark_id)
        return gtsam.PriorFactorPoint2(
            symbol,
            self.solver.calculateEstimatePoint2(symbol),
            gtsam.noiseModel.Isotropic.Sigma(2, PARKING_SIGMA_M),
        )

    # --- weights ------------------------------------------------------------------------

    def _update_weights(self, seen: tuple[int, ...]) -> tuple[int, ...]:
        """The M-step and the gate for the landmarks ``seen``; queue the changes to their
        factors: all of a landmark's when its weight moved past ``weight_step``, a
        sighting's when its gate changed; park a landmark left without any; return the ids
        of those changed."""
        return tuple(i for i in seen if self._apply(i, *self._weight(i)))

    def _apply(self, landmark_id: int, weight: float, gated: list[bool], held: list[bool]) -> bool:
        """Take a landmark's new weight, gate and held sightings; queue the changes to its
        factors; return whether there were any."""
        landmark = self.landmarks[landmark_id]
        carried = [landmark.carries(k) for k in range(len(landmark.poses))]
        landmark.weight, landmark.gated, landmark.held = weight, gated, held
        rescaled = abs(weight - landmark.applied) > self.incremental.weight_step
        if rescaled:
            landmark.applied = weight
        queued = len(self._pending) + len(self._pending_removals)
        for k, was in enumerate(carried):
            wanted = landmark.carries(k)
            if was and (rescaled or not wanted):  # every carried factor is in the smoother
                self._pending_removals.append(landmark.factors[k])
                landmark.factors[k] = -1
            if wanted and (rescaled or not was):
                self._pending.append((landmark_id, k))
        any_carried = any(landmark.carries(k) for k in range(len(landmark.poses)))
        if not any_carried and landmark.parked < 0:
            landmark.position = self._point(landmark_id)
            self._pending.append((landmark_id, -1))
        elif any_carried and landmark.parked >= 0:
            self._pending_removals.append(landmark.parked)
            landmark.parked, landmark.position = -1, None
        return len(self._pending) + len(self._pending_removals) > queued

    def _weight(self, landmark_id: int) -> tuple[float, list[bool], list[bool]]:
        """The landmark's M-step weight, its gated sightings and those held out (beyond
        linearization), at the smoother's estimate."""
        landmark = self.landmarks[landmark_id]
        count = len(landmark.poses)
        z, cov = np.array(landmark.z), np.array(landmark.cov)
        innovation = self._innovations(landmark_id, self._poses_at(landmark.poses), z)
        held = _beyond_linearization(innovation)
        if count <= 1:
            return 1.0, [False] * count, held.tolist()
        mahalanobis = self._mahalanobis(innovation, z, cov)
        owner = np.zeros(count, dtype=np.int64)
        if self.config.mode == 'paper':
            gated = np.zeros(count, dtype=bool)
        else:
            gated = gate_outliers(self.config, mahalanobis, owner, 1)
        weight = float(m_step(self.config, mahalanobis, owner, 1, ~gated)[0])
        return weight, gated.tolist(), held.tolist()

    def _innovations(self, landmark_id: int, poses: FloatArray, z: FloatArray) -> FloatArray:
        """The innovations (K, 2) of sightings z (K, 2) from ``poses`` (K, 3) of the
        landmark where the smoother (or, parked, its own estimate) has it."""
        point = self._position(landmark_id, poses)
        return range_bearing_error(poses, np.repeat(point[None], len(z), axis=0), z)

    def _mahalanobis(self, innovation: FloatArray, z: FloatArray, cov: FloatArray) -> FloatArray:
        """The test's squared Mahalanobis distances (K,) of ``innovation`` (K, 2): the
        sightings' covariances (K, 2, 2) with the model error."""
        tested = covariances_for_test(self.config, cov, z)
        return squared_mahalanobis(innovation, cov if tested is None else tested)

    def _enter(self, landmark_id: int, new: _NewSighting) -> tuple[bool, bool]:
        """Whether a new sighting of a mapped landmark enters gated (the
        landmark's gate, at the smoother's estimate with the sighting added, gates it) and
        whether it is held out (beyond linearization). Either way it carries no factor
        into the update: one step of the smoother with a gross outlier in it cannot be
        taken back by removing the outlier."""
        landmark = self.landmarks[landmark_id]
        if landmark.parked >= 0:
            return False, False
        pose = new.pose
        poses = np.vstack([self._poses_at(landmark.poses), [pose.x(), pose.y(), pose.theta()]])
        z_all, cov_all = np.array([*landmark.z, new.z]), np.array([*landmark.cov, new.cov])
        innovation = self._innovations(landmark_id, poses, z_all)
        held = bool(_beyond_linearization(innovation[-1:])[0])
        if self.config.mode == 'paper':
            return False, held
        mahalanobis = self._mahalanobis(innovation, z_all, cov_all)
        owner = np.zeros(len(mahalanobis), dtype=np.int64)
        gated = bool(gate_outliers(self.config, mahalanobis, owner, 1)[-1])
        if gated and self._predicted_fit(landmark_id, new):
            gated = False  # the estimate, not the sighting, is what is off (drift)
        return gated, held

    def _predicted_fit(self, landmark_id: int, new: _NewSighting) -> bool:
        """Whether a new sighting is within the gate of its predicted innovation covariance:
        the pose's marginal (a new keyframe's propagated from the one before by its
        increment) and the landmark's through the sighting's Jacobians, plus the test's
        covariance (their correlation left out, which only widens it)."""
        gtsam = self.gtsam
        keyframe, z, cov = new.keyframe, new.z, new.cov
        symbol = gtsam.symbol('l', landmark_id)
        tested = covariances_for_test(self.config, cov[None], z[None])
        test_cov = (cov if tested is None else tested[0])[np.ix_([1, 0], [1, 0])]
        factor = gtsam.BearingRangeFactor2D(
            keyframe,
            symbol,
            gtsam.Rot2(float(z[1])),
            float(z[0]),
            gtsam.noiseModel.Gaussian.Covariance(test_cov),
        )
        if new.increment is None:
            pose_cov = self.solver.marginalCovariance(keyframe)
        else:
            relative, increment_cov = new.increment
            adjoint = relative.inverse().AdjointMap()
            previous = self.solver.marginalCovariance(keyframe - 1)
            pose_cov = adjoint @ previous @ adjoint.T + increment_cov
        values = gtsam.Values()
        values.insert(keyframe, new.pose)
        values.insert(symbol, self.solver.calculateEstimatePoint2(symbol))
        jacobian, whitened = factor.linearize(values).jacobian()
        by_pose, by_point = jacobian[:, :3], jacobian[:, 3:]
        innovation_cov = (
            np.eye(2)
            + by_pose @ pose_cov @ by_pose.T
            + by_point @ self.solver.marginalCovariance(symbol) @ by_point.T
        )
        return float(whitened @ np.linalg.solve(innovation_cov, whitened)) <= chi2_quantile(
            1.0 - self.config.gate_probability, 2
        )

    def _poses_at(self, indices: list[int]) -> FloatArray:
        """The estimates of the poses ``indices`` (K, 3), one lookup each (a copy of the
        whole linearization point and delta would cost a pass over the run per call)."""
        moved = [self.solver.calculateEstimatePose2(i) for i in indices]
        return np.array([(p.x(), p.y(), p.theta()) for p in moved]).reshape(-1, 3)

    def _point(self, landmark_id: int) -> FloatArray:
        symbol = self.gtsam.symbol('l', landmark_id)
        return np.asarray(self.solver.calculateEstimatePoint2(symbol), np.float64)

    def _position(self, landmark_id: int, poses: FloatArray) -> FloatArray:
        """Where the landmark is: the smoother's estimate, or, parked, the least-squares
        point of all its sightings from ``poses`` (the first len(landmark.poses) rows; as
        the batch's E-step places a landmark whose rows all carry the floor), refined from
        the last one."""
        landmark = self.landmarks[landmark_id]
        if landmark.parked < 0 or landmark.position is None:
            return self._point(landmark_id)
        count = len(landmark.poses)
        poses, z = poses[:count], np.array(landmark.z)
        information = np.linalg.inv(np.array(landmark.cov))
        point = landmark.position
        for _ in range(PARKED_ITERATIONS):
            innovation = range_bearing_error(poses, np.repeat(point[None], count, axis=0), z)
            _, by_point = range_bearing_error_jacobians(poses, np.repeat(point[None], count, 0))
            weighted = np.swapaxes(by_point, 1, 2) @ information
            hessian = np.einsum('kij,kjl->il', weighted, by_point)
            gradient = np.einsum('kij,kj->i', weighted, innovation)
            step = -np.linalg.lstsq(hessian, gradient, rcond=None)[0]
            point = point + step
            if np.linalg.norm(step) < 1e-6:
                break
        landmark.position = point
        return point

    # --- what it holds ------------------------------------------------------------------

    @property
    def moveable(self) -> frozenset[int]:
        """The landmarks whose weight is below the moveable threshold."""
        threshold = self.config.moveable_threshold
        return frozenset(i for i, lm in self.landmarks.items() if lm.weight < threshold)

    @property
    def weights(self) -> dict[int, float]:
        """The current weight of every landmark, by id."""
        return {i: lm.weight for i, lm in self.landmarks.items()}

    def poses(self) -> FloatArray:
        """The smoother's keyframe poses (N, 3) as (x m, y m, theta rad)."""
        return self._poses_at(list(range(self.num_keyframes)))

    def landmark_positions(self) -> dict[int, FloatArray]:
        """The landmark positions, by id: the smoother's, a parked landmark's own."""
        return {i: self._position(i, self._poses_at(lm.poses)) for i, lm in self.landmarks.items()}

    def placed_sightings(self, landmark_id: int) -> tuple[list[int], FloatArray, FloatArray]:
        """Where the landmark was seen, in the order it was: the keyframes, the sightings
        placed in the map through the smoother's poses (S, 2) m, and their covariances
        (S, 2, 2) m^2 from the sensor's alone (the poses' own uncertainty is left out: a
        marginal per sighting would cost a solve each)."""
        landmark = self.landmarks[landmark_id]
        poses = self._poses_at(landmark.poses)
        z, cov = np.array(landmark.z).reshape(-1, 2), np.array(landmark.cov).reshape(-1, 2, 2)
        _, by_z = sighting_jacobians(poses, z)
        covariances = by_z @ cov @ np.swapaxes(by_z, 1, 2)
        return list(landmark.poses), range_bearing_to_point(poses, z), covariances


def _beyond_linearization(innovation: FloatArray) -> np.ndarray:
    """Sightings (K,) whose bearing innovation (K, 2) exceeds a right angle: the smoother
    has the landmark in the other half-plane from where it was seen, so the bearing's
    linearization there points no way toward the measurement and a Gauss-Newton step with
    the factor is no step toward it. They stay out of the smoother (the test still counts
    them) until the estimate brings them within it."""
    result: np.ndarray = np.abs(innovation[:, 1]) > np.pi / 2
    return result
