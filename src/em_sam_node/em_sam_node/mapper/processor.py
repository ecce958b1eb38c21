"""em_sam_mapper's processor: collects increments and observations, runs EM-SAM on demand,
feeds the online smoother; see docs/design/em_sam_core.md."""

from __future__ import annotations

import bisect
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from em_sam_node.core.assembly import MappingData, build_problem, dead_reckoning, is_covariance
from em_sam_node.core.em import anchored_problem, run_em
from em_sam_node.core.em_types import EmConfig, EmResult
from em_sam_node.core.incremental import IncrementalEmSam
from em_sam_node.core.incremental_types import UpdateStats
from em_sam_node.core.inputs import Increment, Observation
from em_sam_node.core.localization import (
    KnownMap,
    run_localization,
    static_joint_covariance,
)
from em_sam_node.core.marginals import marginal_pose_covariance
from em_sam_node.core.problem import Estimate
from em_sam_node.core.sightings import Sightings, sightings_of
from slam_core.arrays import FloatArray, IntArray
from slam_core.geometry.se2 import apply_increment, compose, inverse
from slam_core.params import NON_NEGATIVE, POSITIVE, check_fields, ruled

ONLINE_REBUILDS = 1  # a failed smoother is rebuilt this often before it is stopped


@dataclass(frozen=True)
class MapperConfig:
    """Validated em_sam_mapper settings."""

    em: EmConfig
    stamp_tolerance_s: float = ruled(0.005, range=NON_NEGATIVE)
    prior_sigma: tuple[float, float, float] = ruled((1e-3, 1e-3, 1e-3), range=POSITIVE, length=3)
    pending_timeout_s: float = ruled(10.0, range=POSITIVE)
    online: bool = True
    known_map: KnownMap | None = None
    start_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    start_sigma: tuple[float, float, float] = (0.5, 0.5, 0.2618)

    def __post_init__(self) -> None:
        check_fields(self, prefix='parameter ')
        if self.known_map is not None and self.online:
            raise ValueError('localization on a saved map runs the full pass only (online off)')

    @property
    def localizing(self) -> bool:
        """True on a saved map (``known_map``): keyframe 0 at ``start_pose``, landmarks fixed."""
        return self.known_map is not None


class MapperProcessor:
    """The mapper's state: keyframe chain, observations, and the latest EM-SAM result."""

    def __init__(self, config: MapperConfig, warn: Callable[[str], None] | None = None) -> None:
        self.config = config
        self.warn = warn if warn is not None else (lambda _message: None)
        self.stamps_ns: list[int] = []
        self.odom_poses: list[FloatArray] = []
        self.increments: list[Increment] = []  # increments[i] ends at keyframe i + 1
        self.observations: list[tuple[int, Observation]] = []  # (keyframe, observation)
        self.pending: list[Observation] = []
        self.result: EmResult | None = None
        self.result_data: MappingData | None = None  # what self.result was solved from
        self.result_keyframes = 0
        self.dropped_observations = 0
        self.before_start_observations = 0
        self.dropped_increments = 0
        self.duplicate_increments = 0
        self.duplicate_observations = 0
        self.seen_observations: set[tuple[int, int]] = set()  # (stamp ns, landmark id)
        self.online: IncrementalEmSam | None = None  # config.online, from the first keyframe
        self.online_last: UpdateStats | None = None  # the smoother's latest update
        self.online_max_s = 0.0  # its longest update, s
        self._unfed: list[int] = []  # rows of self.observations not in the smoother yet
        self.online_failures: list[str] = []  # each failed smoother update: where and why
        self.online_stopped = False  # it failed again after its rebuild

    # -- input ----------------------------------------------------------------------------
    def add_increment(self, increment: Increment) -> None:
        """Append an increment; it must start at the latest keyframe."""
        if not (np.all(np.isfinite(increment.u)) and is_covariance(increment.covariance)):
            self.warn(
                f'increment {increment.stamp_from_ns}->{increment.stamp_to_ns} ns has '
                'non-finite values or a covariance that is not positive definite; dropped'
            )
            self.dropped_increments += 1
            return
        if self.stamps_ns and increment.stamp_to_ns <= self.stamps_ns[-1]:
            index = bisect.bisect_left(self.stamps_ns, increment.stamp_to_ns)
            if (
                index > 0
                and self.stamps_ns[index] == increment.stamp_to_ns
                and self.stamps_ns[index - 1] == increment.stamp_from_ns
            ):
                self.duplicate_increments += 1  # held already (a replayed history)
                return
        if not self.stamps_ns:
            self.stamps_ns.append(increment.stamp_from_ns)
            self.odom_poses.append(increment.odom_pose_from.copy())
        elif increment.stamp_from_ns != self.stamps_ns[-1]:
            self.warn(
                f'increment starts at {increment.stamp_from_ns} ns but the last keyframe '
                f'is {self.stamps_ns[-1]} ns; dropped (out of order or missing increments)'
            )
            self.dropped_increments += 1
            return
        if increment.stamp_to_ns <= increment.stamp_from_ns:
            self.warn(
                f'increment {increment.stamp_from_ns}->{increment.stamp_to_ns} ns does not '
                'go forward in time; dropped'
            )
            self.dropped_increments += 1
            return
        self.stamps_ns.append(increment.stamp_to_ns)
        self.odom_poses.append(increment.odom_pose_to.copy())
        self.increments.append(increment)
        self._attach_pending()
        if self.config.online:
            self._feed(self.num_keyframes - 1)

    # -- online ---------------------------------------------------------------------------
    def _feed(self, count: int) -> None:
        """Put the keyframes before ``count`` that are not in the smoother yet into it; a
        smoother whose update fails is rebuilt from keyframe 0 once, then stopped."""
        if self.online_stopped:
            return
        try:
            self._feed_smoother(count)
        except RuntimeError as err:  # GTSAM: an ill-posed update (IndeterminateLinearSystem)
            at = self.online.num_keyframes if self.online is not None else 0
            reason = next((line for line in str(err).splitlines() if line.strip()), repr(err))
            self.online_failures.append(f'keyframe {at}: {reason.strip()}')
            self.online, self.online_last, self._unfed = None, None, []
            self.online_stopped = len(self.online_failures) > ONLINE_REBUILDS
            then = (
                'stopped for this run (the full pass goes on)'
                if self.online_stopped
                else 'rebuilt from keyframe 0 with the next keyframe'
            )
            self.warn(f'online smoother failed at keyframe {at} ({reason.strip()}); {then}')

    def _feed_smoother(self, count: int) -> None:
        if self.online is None:  # every observation held waits for it (a resumed mapper's too)
            sigma = np.array(self.config.prior_sigma)
            self.online = IncrementalEmSam(self.config.em, self.odom_poses[0], np.diag(sigma**2))
            self._unfed = list(range(len(self.observations)))
        smoother = self.online
        while smoother.num_keyframes < count:
            index = smoother.num_keyframes
            rows = [row for row in self._unfed if self.observations[row][0] <= index]
            self._unfed = [row for row in self._unfed if self.observations[row][0] > index]
            now, late = [], []
            for row in rows:
                keyframe, seen = self.observations[row]
                item = (seen.landmark_id, seen.z, seen.covariance)
                if keyframe == index:
                    now.append(item)
                else:
                    late.append((keyframe, *item))
            increment = self.increments[index - 1] if index > 0 else None
            odometry = None if increment is None else (increment.u, increment.covariance)
            self.online_last = smoother.add_keyframe(odometry, now, late)
            self.online_max_s = max(self.online_max_s, self.online_last.seconds)

    @property
    def online_waiting(self) -> int:
        """Observations attached to keyframes that are not in the smoother yet."""
        return len(self._unfed)

    def online_sightings(self, landmark_id: int) -> Sightings | None:
        """Every sighting of a landmark the smoother holds, most recent first, or None."""
        if self.online is None or landmark_id not in self.online.landmarks:
            return None
        keyframes, positions, covariances = self.online.placed_sightings(landmark_id)
        stamps = np.array(self.stamps_ns, dtype=np.int64)[keyframes]
        order = np.argsort(-stamps, kind='stable')
        return Sightings(stamps[order], positions[order], covariances[order])

    @property
    def online_moveable(self) -> frozenset[int]:
        """The smoother's moveable set (empty before its first keyframe or offline)."""
        return self.online.moveable if self.online is not None else frozenset()

    def add_observation(self, observation: Observation) -> None:
        """Attach an observation to its keyframe, or keep it until the keyframe arrives."""
        key = (observation.stamp_ns, observation.landmark_id)
        if key in self.seen_observations:
            self.duplicate_observations += 1  # taken already (a replayed history)
            return
        self.seen_observations.add(key)
        z, cov = observation.z, observation.covariance
        if not (np.all(np.isfinite(z)) and is_covariance(cov) and z[0] > 0):
            self.dropped_observations += 1
            self.warn(
                f'observation of landmark {observation.landmark_id} at '
                f'{observation.stamp_ns} ns has an invalid range/bearing/covariance; dropped'
            )
            return
        if not self._attach(observation):
            self.pending.append(observation)

    def _attach(self, observation: Observation) -> bool:
        tolerance = round(self.config.stamp_tolerance_s * 1e9)
        index = bisect.bisect_left(self.stamps_ns, observation.stamp_ns - tolerance)
        if (
            index < len(self.stamps_ns)
            and abs(self.stamps_ns[index] - observation.stamp_ns) <= tolerance
        ):
            self._unfed.append(len(self.observations))
            self.observations.append((index, observation))
            return True
        return False

    def _attach_pending(self) -> None:
        if not self.pending:
            return
        latest = self.stamps_ns[-1]
        timeout = round(self.config.pending_timeout_s * 1e9)
        still = []
        for observation in self.pending:
            if self._attach(observation):
                continue
            if observation.stamp_ns < self.stamps_ns[0]:
                self.before_start_observations += 1
                self.warn(
                    f'observation of landmark {observation.landmark_id} at '
                    f'{observation.stamp_ns} ns is older than the first keyframe '
                    f'({self.stamps_ns[0]} ns): seen before the odometry started; not used'
                )
                continue
            if latest - observation.stamp_ns > timeout:
                self.dropped_observations += 1
                self.warn(
                    f'observation of landmark {observation.landmark_id} at '
                    f'{observation.stamp_ns} ns matches no keyframe (its keyframe never '
                    'came); dropped'
                )
                continue
            still.append(observation)
        self.pending = still

    # -- solving --------------------------------------------------------------------------
    @property
    def num_keyframes(self) -> int:
        """Keyframes collected so far."""
        return len(self.stamps_ns)

    def data(self) -> MappingData:
        """Return everything collected as MappingData (keyframe 0 anchored at its odom pose)."""
        count = len(self.increments)
        observations = sorted(self.observations, key=lambda item: item[0])
        sigma = np.array(self.config.prior_sigma)
        prior_pose = self.odom_poses[0].copy() if self.odom_poses else np.zeros(3)
        if self.config.localizing:
            prior_pose = np.array(self.config.start_pose, dtype=float)
            sigma = np.array(self.config.start_sigma)
        return MappingData(
            keyframe_stamps_ns=np.array(self.stamps_ns, dtype=np.int64),
            odometry_from=np.arange(count, dtype=np.int64),
            odometry_to=np.arange(1, count + 1, dtype=np.int64),
            odometry_u=np.array([i.u for i in self.increments]).reshape(count, 3),
            odometry_cov=np.array([i.covariance for i in self.increments]).reshape(count, 3, 3),
            obs_keyframe=np.array([k for k, _ in observations], dtype=np.int64),
            obs_landmark_id=np.array([o.landmark_id for _, o in observations], dtype=np.int64),
            obs_z=np.array([o.z for _, o in observations]).reshape(-1, 2),
            obs_cov=np.array([o.covariance for _, o in observations]).reshape(-1, 2, 2),
            prior_pose=prior_pose,
            prior_cov=np.diag(sigma**2),
        )

    def optimize(self, *, record_snapshots: bool = False) -> EmResult | None:
        """Run EM-SAM on everything collected, warm-started from the previous result."""
        if self.num_keyframes < 2:
            self.warn('nothing to optimize yet: fewer than two keyframes')
            return None
        data = self.data()
        if self.config.known_map is not None:
            self.result = run_localization(
                data, self.config.known_map, self.config.em, initial_poses=self._warm_start(data)
            )
        else:
            self.result = run_em(
                data,
                self.config.em,
                initial_poses=self._warm_start(data),
                record_snapshots=record_snapshots,
            )
        self.result_data = data
        self.result_keyframes = data.num_keyframes
        return self.result

    def _warm_start(self, data: MappingData) -> FloatArray | None:
        """Previous poses for old keyframes, odometry composed onto them for new ones."""
        if self.result is None:
            return None
        poses = dead_reckoning(data)
        known = min(self.result_keyframes, data.num_keyframes)
        poses[:known] = self.result.poses[:known]
        for index in range(known, data.num_keyframes):
            poses[index] = apply_increment(
                poses[index - 1][None], data.odometry_u[index - 1][None]
            )[0]
        return poses

    def use_map(
        self,
        known_map: KnownMap,
        start_pose: tuple[float, float, float],
        start_sigma: tuple[float, float, float],
    ) -> None:
        """Localize on ``known_map`` from now on (drops the result so far and the smoother)."""
        self.config = dataclasses.replace(
            self.config,
            known_map=known_map,
            start_pose=start_pose,
            start_sigma=start_sigma,
            online=False,
        )
        self.result = self.result_data = None
        self.result_keyframes = 0
        self.online, self.online_last, self._unfed = None, None, []

    # -- queries --------------------------------------------------------------------------
    def map_to_odom(self) -> FloatArray | None:
        """Return the map->odom transform (x, y, theta) at the latest solved keyframe."""
        if self.result is None:
            return None
        index = self.result_keyframes - 1
        return compose(self.result.poses[index][None], inverse(self.odom_poses[index][None]))[0]

    def static_joint_covariance(self) -> tuple[IntArray, FloatArray] | None:
        """The static landmarks' ids (S,) and joint covariance (2S, 2S) m^2 of a mapping
        solution; None before a solve and on a saved map."""
        if self.result is None or self.result_data is None or self.config.localizing:
            return None
        return static_joint_covariance(self.result_data, self.result)

    def latest_pose(self) -> tuple[int, FloatArray, FloatArray] | None:
        """The latest solved keyframe: stamp int ns, pose (x m, y m, theta rad), map frame, and
        its marginal covariance (3, 3)."""
        result, data = self.result, self.result_data
        if result is None or data is None or not len(result.poses):
            return None
        moveable = result.landmark_ids[result.moveable].tolist()
        built = build_problem(data, exclude_ids=moveable)
        keep = np.isin(result.landmark_ids, built.landmark_ids)
        problem, _ = anchored_problem(built, result.poses)
        if self.config.known_map is not None:
            fixed = np.isin(built.landmark_ids, self.config.known_map.landmark_ids)
            problem = dataclasses.replace(problem, fixed_landmarks=fixed)
        index = len(result.poses) - 1
        estimate = Estimate(result.poses, result.positions[keep])
        covariance = marginal_pose_covariance(problem, estimate, [index])[0]
        return int(data.keyframe_stamps_ns[index]), result.poses[index].copy(), covariance

    def find_landmark(self, landmark_id: int) -> Sightings | None:
        """Return every sighting of a landmark placed in the map, most recent first."""
        result, data = self.result, self.result_data
        if result is None or data is None or landmark_id not in set(result.landmark_ids.tolist()):
            return None
        if landmark_id in result.sightings:
            return result.sightings[landmark_id]
        # ``data`` is what ``result`` was solved from: newer keyframes have no solution yet.
        built = build_problem(data, exclude_ids=result.landmark_ids[result.moveable].tolist())
        keep = np.isin(result.landmark_ids, built.landmark_ids)
        solved = Estimate(result.poses, result.positions[keep])
        return sightings_of(data, built.problem, solved, [landmark_id])[landmark_id]
