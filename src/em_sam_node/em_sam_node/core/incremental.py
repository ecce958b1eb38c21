"""EM-SAM online: GTSAM's iSAM2 in a fixed-lag smoother, with the EM weights updated where a
keyframe lands; see docs/design/em_sam_core.md and docs/design/em_sam_online.md."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.em_weights import (
    chi2_quantile,
    squared_mahalanobis,
    weight_model,
)
from em_sam_node.core.factors import range_bearing_error
from em_sam_node.core.incremental_parts import (
    between_of_increment,
    beyond_linearization,
    least_squares_point,
    load_gtsam,
)
from em_sam_node.core.incremental_types import (
    ANCHOR,
    FOLDED,
    PARKING_SIGMA_M,
    PLACE_SIGHTINGS,
    IncrementalConfig,
    LandmarkTrack,
    NewSighting,
    UpdateStats,
)
from em_sam_node.core.sightings import sighting_jacobians
from slam_core.arrays import FloatArray
from slam_core.geometry.se2 import range_bearing_to_point


class IncrementalEmSam:
    """The online smoother. Keyframes come in order, one per call."""

    def __init__(
        self,
        config: EmConfig,
        prior_pose: FloatArray,
        prior_cov: FloatArray,
        incremental: IncrementalConfig | None = None,
    ) -> None:
        self.gtsam = load_gtsam()
        self.config = config
        self.model = weight_model(config)
        self.incremental = incremental or IncrementalConfig()
        self.prior_pose = np.asarray(prior_pose, np.float64).reshape(3)
        self.prior_cov = np.asarray(prior_cov, np.float64).reshape(3, 3)
        self.landmarks: dict[int, LandmarkTrack] = {}
        self.num_keyframes = 0
        self._pending_removals: list[int] = []
        self._pending: list[tuple[int, int]] = []  # (landmark id, sighting) to (re)add
        self._reviving: list[int] = []  # landmarks coming back in this update
        self._first_live = 0  # poses before it have left the smoother
        self._frozen_poses: list[tuple[float, float, float]] = []  # their last estimates
        self._sightings_at: dict[int, list[tuple[int, int]]] = {}  # live pose: (id, k)
        self._returns = 0  # keys given to landmarks that came back
        self.dropped_late = 0  # late sightings of keyframes that had left the smoother
        params = self.gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.incremental.relinearize_threshold)
        params.relinearizeSkip = self.incremental.relinearize_skip
        # check only the cliques an update touched for relinearization, not every variable:
        # per-update cost independent of the run's length
        params.enablePartialRelinearizationCheck = True
        # iSAM2 behind GTSAM's fixed-lag smoother, which marginalizes the keys whose
        # timestamp is more than the horizon behind the newest. A timestamp is the block
        # of a tenth of the horizon that holds the keyframe (a pose's own, the latest a
        # landmark was seen from): marginalizing re-eliminates the path from the oldest
        # pose to the root, the whole window, so it happens once a block, not per keyframe
        horizon = self.incremental.horizon
        self._block = max(1, horizon // 10)
        lag = horizon / self._block if horizon else float('inf')
        self.solver = self.gtsam.IncrementalFixedLagSmoother(lag, params)

    # --- keyframes ----------------------------------------------------------------------

    def add_keyframe(
        self,
        odometry: tuple[FloatArray, FloatArray] | None,
        sightings: Sequence[tuple[int, FloatArray, FloatArray]],
        late: Sequence[tuple[int, int, FloatArray, FloatArray]] = (),
    ) -> UpdateStats:
        """Add the next keyframe: increment (u (3,), cov (3, 3)) or None for the first, sightings
        (id, (range m, bearing rad), cov (2, 2)) and ``late`` ones (keyframe index first)."""
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
        block, horizon = self._block, self.incremental.horizon
        cutoff = index // block - horizon / block  # in blocks, as the smoother's timestamps
        end = block * math.ceil(cutoff) if horizon and cutoff > 0 else 0  # poses before leave
        for keyframe, landmark_id, z, cov in [*late, *((index, *s) for s in sightings)]:
            if not 0 <= keyframe <= index:
                raise ValueError(f'a sighting of keyframe {keyframe}: there are {index + 1}')
            if keyframe < max(end, self._first_live):
                self.dropped_late += 1  # its pose leaves the smoother: nothing to attach it to
                continue
            landmark_id = int(landmark_id)
            landmark = self.landmarks.get(landmark_id)
            if landmark and landmark.retired is not None and landmark_id not in self._reviving:
                self._revive(landmark_id, values)
            z = np.asarray(z, np.float64).reshape(2)
            cov = np.asarray(cov, np.float64).reshape(2, 2)
            seen_from = start if keyframe == index else self._pose(keyframe)
            increment = (relative, covariance[0]) if keyframe == index and index > 0 else None
            gated, held, explained = (
                self._enter(landmark_id, NewSighting(keyframe, seen_from, increment, z, cov))
                if landmark and landmark_id not in created
                else (False, False, False)  # this keyframe maps it: not in the smoother yet
            )
            if landmark is None:
                created.add(landmark_id)
                landmark = LandmarkTrack(gtsam.symbol('l', landmark_id))
                self.landmarks[landmark_id] = landmark
                point = seen_from.transformFrom(
                    gtsam.Point2(z[0] * np.cos(z[1]), z[0] * np.sin(z[1]))
                )
                values.insert(landmark.key, point)
            self._sightings_at.setdefault(int(keyframe), []).append(
                (landmark_id, len(landmark.poses))
            )
            landmark.last = max(landmark.last, int(keyframe))
            landmark.frozen.append(False)
            landmark.poses.append(int(keyframe))
            landmark.z.append(z)
            landmark.cov.append(cov)
            landmark.factors.append(-1)
            landmark.gated.append(gated)
            landmark.held.append(held)
            landmark.explained.append(explained)
            if landmark.carries(len(landmark.poses) - 1):
                self._pending.append((landmark_id, len(landmark.poses) - 1))
            sighted.add(landmark_id)
        self.num_keyframes += 1
        timestamps = {index: float(index // block)}
        for landmark_id in sighted:
            landmark = self.landmarks[landmark_id]
            timestamps[landmark.key] = float(landmark.last // block)
        if end > self._first_live:
            self._freeze(end)
        self._update(factors, values, timestamps)
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

    def _update(
        self, factors: Any, values: Any, timestamps: dict[int, float] | None = None
    ) -> None:
        """One smoother update with ``factors``, ``values`` and the queued changes."""
        queued, self._pending = self._pending, []
        for landmark_id, k in queued:
            if k >= 0:
                factors.add(self._sighting_factor(landmark_id, k))
            else:
                factors.add(
                    self._anchor(landmark_id) if k == ANCHOR else self._parking(landmark_id)
                )
        removals, self._pending_removals = self._pending_removals, []
        self.solver.update(factors, values, timestamps or {}, removals)
        result = self.solver.getISAM2Result()
        new_indices = list(result.getNewFactorsIndices())  # in the order they were added
        for (landmark_id, k), factor in zip(
            queued, new_indices[len(new_indices) - len(queued) :], strict=True
        ):
            landmark = self.landmarks[landmark_id]
            if k >= 0:
                landmark.factors[k] = int(factor)
            elif k == ANCHOR:
                landmark.anchor = int(factor)
            else:
                landmark.parked = int(factor)
        for landmark_id in self._reviving:  # in the smoother now
            self.landmarks[landmark_id].retired = None
        self._reviving = []

    def _pose(self, index: int) -> Any:
        if index < self._first_live:
            return self.gtsam.Pose2(*self._frozen_poses[index])
        return self.solver.calculateEstimatePose2(index)

    def _sighting_factor(self, landmark_id: int, k: int) -> Any:
        gtsam = self.gtsam
        landmark = self.landmarks[landmark_id]
        cov = landmark.cov[k][::-1, ::-1] / landmark.applied  # (bearing, range)
        z = landmark.z[k]
        return gtsam.BearingRangeFactor2D(
            landmark.poses[k],
            landmark.key,
            gtsam.Rot2(float(z[1])),
            float(z[0]),
            gtsam.noiseModel.Gaussian.Covariance(cov),
        )

    def _parking(self, landmark_id: int) -> Any:
        """A prior that holds a landmark without sightings where it is."""
        gtsam = self.gtsam
        return gtsam.PriorFactorPoint2(
            self.landmarks[landmark_id].key,
            gtsam.Point2(*self._point(landmark_id)),
            gtsam.noiseModel.Isotropic.Sigma(2, PARKING_SIGMA_M),
        )

    def _anchor(self, landmark_id: int) -> Any:
        """The prior that holds a returning landmark where it was when it left."""
        gtsam = self.gtsam
        landmark = self.landmarks[landmark_id]
        assert landmark.anchor_prior is not None
        point, cov = landmark.anchor_prior
        return gtsam.PriorFactorPoint2(
            landmark.key,
            gtsam.Point2(*point),
            gtsam.noiseModel.Gaussian.Covariance(cov / landmark.applied),
        )

    # --- the horizon --------------------------------------------------------------------

    def _freeze(self, end: int) -> None:
        """Keep the last estimates of what leaves before ``end``; mark what the marginal takes."""
        poses = list(range(self._first_live, end))
        leaving = sorted(
            {
                landmark_id
                for p in poses
                for landmark_id, _ in self._sightings_at.get(p, ())
                if self.landmarks[landmark_id].last < end
            }
        )
        self._frozen_poses.extend(tuple(row) for row in self._poses_at(poses).tolist())
        for landmark_id in leaving:
            landmark = self.landmarks[landmark_id]
            cov = (
                np.eye(2) * PARKING_SIGMA_M**2
                if landmark.parked >= 0
                else self.solver.marginalCovariance(landmark.key)
            )
            point = self._position(landmark_id, self._poses_at(landmark.poses))
            landmark.retired, landmark.anchor_prior = (point, cov), None
            landmark.anchor = landmark.parked = -1
            landmark.position = None
        for p in poses:
            for landmark_id, k in self._sightings_at.pop(p, ()):
                landmark = self.landmarks[landmark_id]
                landmark.frozen[k] = True
                if landmark.factors[k] >= 0:
                    landmark.factors[k] = FOLDED
        self._first_live = end

    def _revive(self, landmark_id: int, values: Any) -> None:
        """Bring a landmark that left back under a new key: anchored, or parked at the floor."""
        gtsam = self.gtsam
        landmark = self.landmarks[landmark_id]
        assert landmark.retired is not None
        landmark.key = gtsam.symbol('r', self._returns)
        self._returns += 1
        values.insert(landmark.key, gtsam.Point2(*landmark.retired[0]))
        landmark.anchor_prior = landmark.retired
        if landmark.wants_anchor():
            self._pending.append((landmark_id, ANCHOR))
        else:
            landmark.position = landmark.retired[0]
            self._pending.append((landmark_id, -1))
        self._reviving.append(landmark_id)

    # --- weights ------------------------------------------------------------------------

    def _update_weights(self, seen: tuple[int, ...]) -> tuple[int, ...]:
        """The M-step and gate for the landmarks ``seen``; queue their factors' changes; return
        the ids changed."""
        return tuple(i for i in seen if self._apply(i, *self._weight(i)))

    def _apply(self, landmark_id: int, weight: float, gated: list[bool], held: list[bool]) -> bool:
        """Take a landmark's new weight, gate and held sightings; return whether any changed."""
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
        if landmark.anchor >= 0 and (rescaled or not landmark.wants_anchor()):
            self._pending_removals.append(landmark.anchor)
            landmark.anchor = -1
        if landmark.wants_anchor() and landmark.anchor < 0:
            self._pending.append((landmark_id, ANCHOR))
        any_carried = landmark.wants_anchor() or any(
            landmark.carries(k) for k in range(len(landmark.poses))
        )
        if not any_carried and landmark.parked < 0:
            landmark.position = self._point(landmark_id)
            self._pending.append((landmark_id, -1))
        elif any_carried and landmark.parked >= 0:
            self._pending_removals.append(landmark.parked)
            landmark.parked, landmark.position = -1, None
        return len(self._pending) + len(self._pending_removals) > queued

    def _weight(self, landmark_id: int) -> tuple[float, list[bool], list[bool]]:
        """The landmark's M-step weight, its gated and its held-out sightings, at the estimate."""
        landmark = self.landmarks[landmark_id]
        count = len(landmark.poses)
        z, cov = np.array(landmark.z), np.array(landmark.cov)
        poses = self._poses_at(landmark.poses)
        innovation = self._innovations(landmark_id, poses, z)
        held = beyond_linearization(innovation)
        if count <= 1:
            return 1.0, [False] * count, held.tolist()
        mahalanobis = self._mahalanobis(innovation, z, cov)
        owner = np.zeros(count, dtype=np.int64)
        gated = self.model.gate(mahalanobis, owner, 1)
        if self.model.gates:
            beyond = mahalanobis > chi2_quantile(1.0 - self.config.gate_probability, 2)
            gated &= ~self._seen_elsewhere(poses, z, cov, beyond & ~np.array(landmark.explained))
        weight = float(self.model.m_step(mahalanobis, owner, 1, ~gated)[0])
        return weight, gated.tolist(), held.tolist()

    def _seen_elsewhere(
        self, poses: FloatArray, z: FloatArray, cov: FloatArray, beyond: np.ndarray
    ) -> np.ndarray:
        """The landmark's latest sightings (mask, K) that make another place, not misreads."""
        config = self.config
        within = np.flatnonzero(~beyond)
        run = len(beyond) - (int(within[-1]) + 1 if len(within) else 0)
        result = np.zeros(len(z), dtype=bool)
        if run < PLACE_SIGHTINGS:
            return result
        rows = slice(len(z) - run, None)
        tested = self.model.test_covariances(cov[rows], z[rows])
        test_cov = cov[rows] if tested is None else tested
        start = range_bearing_to_point(poses[rows][-1:], z[rows][-1:])[0]
        point = least_squares_point(poses[rows], z[rows], test_cov, start)
        innovation = range_bearing_error(poses[rows], point, z[rows])
        level = chi2_quantile(1.0 - config.false_alarm_probability, 2 * run - 2)
        result[rows] = squared_mahalanobis(innovation, test_cov).sum() <= level
        return result

    def _innovations(self, landmark_id: int, poses: FloatArray, z: FloatArray) -> FloatArray:
        """The innovations (K, 2) of sightings z (K, 2) from ``poses`` (K, 3) of the landmark."""
        point = self._position(landmark_id, poses)
        return range_bearing_error(poses, point, z)

    def _mahalanobis(self, innovation: FloatArray, z: FloatArray, cov: FloatArray) -> FloatArray:
        """The test's squared Mahalanobis distances (K,) of ``innovation`` (K, 2)."""
        tested = self.model.test_covariances(cov, z)
        return squared_mahalanobis(innovation, cov if tested is None else tested)

    def _enter(self, landmark_id: int, new: NewSighting) -> tuple[bool, bool, bool]:
        """Whether a new sighting of a mapped landmark enters gated, is held out, and is within
        its predicted innovation."""
        landmark = self.landmarks[landmark_id]
        if landmark.parked >= 0:
            return False, False, False
        pose = new.pose
        poses = np.vstack([self._poses_at(landmark.poses), [pose.x(), pose.y(), pose.theta()]])
        z_all, cov_all = np.array([*landmark.z, new.z]), np.array([*landmark.cov, new.cov])
        innovation = self._innovations(landmark_id, poses, z_all)
        held = bool(beyond_linearization(innovation[-1:])[0])
        if not self.model.gates:
            return False, held, False
        mahalanobis = self._mahalanobis(innovation, z_all, cov_all)
        owner = np.zeros(len(mahalanobis), dtype=np.int64)
        gated = bool(self.model.gate(mahalanobis, owner, 1)[-1])
        beyond = mahalanobis[-1] > chi2_quantile(1.0 - self.config.gate_probability, 2)
        explained = bool(beyond and self._predicted_fit(landmark_id, new))
        # explained: the estimate, not the sighting, is what is off (drift)
        return gated and not explained, held, explained

    def _predicted_fit(self, landmark_id: int, new: NewSighting) -> bool:
        """Whether a new sighting is within the gate of its predicted innovation covariance."""
        gtsam = self.gtsam
        keyframe, z, cov = new.keyframe, new.z, new.cov
        landmark = self.landmarks[landmark_id]
        symbol = landmark.key
        tested = self.model.test_covariances(cov[None], z[None])
        # (bearing, range), as GTSAM orders them
        test_cov = np.ascontiguousarray((cov if tested is None else tested[0])[::-1, ::-1])
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
        values.insert(symbol, gtsam.Point2(*self._point(landmark_id)))
        jacobian, whitened = factor.linearize(values).jacobian()
        by_pose, by_point = jacobian[:, :3], jacobian[:, 3:]
        point_cov = (
            landmark.retired[1]
            if landmark.retired is not None
            else self.solver.marginalCovariance(symbol)
        )
        innovation_cov = (
            np.eye(2) + by_pose @ pose_cov @ by_pose.T + by_point @ point_cov @ by_point.T
        )
        return float(whitened @ np.linalg.solve(innovation_cov, whitened)) <= chi2_quantile(
            1.0 - self.config.gate_probability, 2
        )

    def _poses_at(self, indices: list[int]) -> FloatArray:
        """The estimates of the poses ``indices`` (K, 3), one lookup each."""
        first, frozen, solver = self._first_live, self._frozen_poses, self.solver
        rows = []
        for i in indices:
            if i < first:
                rows.append(frozen[i])
            else:
                pose = solver.calculateEstimatePose2(i)
                rows.append((pose.x(), pose.y(), pose.theta()))
        return np.array(rows, dtype=np.float64).reshape(-1, 3)

    def _point(self, landmark_id: int) -> FloatArray:
        """The smoother's estimate of a landmark, or where it was while it is out."""
        landmark = self.landmarks[landmark_id]
        if landmark.retired is not None:
            return np.asarray(landmark.retired[0], np.float64)
        return np.asarray(self.solver.calculateEstimatePoint2(landmark.key), np.float64)

    def _position(self, landmark_id: int, poses: FloatArray) -> FloatArray:
        """Where the landmark is (2,): the smoother's estimate, or parked, its least squares."""
        landmark = self.landmarks[landmark_id]
        if landmark.parked < 0 or landmark.position is None:
            return self._point(landmark_id)
        count = len(landmark.poses)
        landmark.position = least_squares_point(
            poses[:count], np.array(landmark.z), np.array(landmark.cov), landmark.position
        )
        return landmark.position

    # --- what it holds ------------------------------------------------------------------

    @property
    def moveable(self) -> frozenset[int]:
        """The landmarks whose weight is below the moveable threshold."""
        threshold = self.config.moveable_threshold
        return frozenset(i for i, lm in self.landmarks.items() if lm.weight < threshold)

    @property
    def kept_from(self) -> int:
        """The oldest keyframe still in the smoother (older ones are marginalized)."""
        return self._first_live

    @property
    def returned(self) -> int:
        """How many times a landmark that had left the smoother came back into it."""
        return self._returns

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
        """Where the landmark was seen, in order: keyframes, points (S, 2) m and the sensor's
        covariances (S, 2, 2) m^2, placed through the smoother's poses."""
        landmark = self.landmarks[landmark_id]
        poses = self._poses_at(landmark.poses)
        z, cov = np.array(landmark.z).reshape(-1, 2), np.array(landmark.cov).reshape(-1, 2, 2)
        _, by_z = sighting_jacobians(poses, z)
        covariances = by_z @ cov @ np.swapaxes(by_z, 1, 2)
        return list(landmark.poses), range_bearing_to_point(poses, z), covariances
