"""Offline replay: a bag through the nodes' processors, and its ground truth; see
docs/design/em_sam_core.md."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from em_sam_node.core.assembly import MappingData
from em_sam_node.core.em_types import EmConfig
from em_sam_node.mapper.conversions import (
    increment_from_message,
    observations_from_message,
)
from em_sam_node.mapper.processor import MapperConfig, MapperProcessor
from em_sam_node.odometry_ingest.conversions import odometry_pose
from em_sam_node.odometry_ingest.processor import IngestConfig, OdometryIngest
from slam_core.arrays import FloatArray, IntArray
from slam_core.errors import BagError
from slam_core.geometry.se2 import wrap_angle
from slam_core.stamps import stamp_to_ns
from slam_ros.bag.source import BagSource
from slam_ros.typesys import TypeRegistry

ODOM_TOPIC = '/odom'
INCREMENTS_TOPIC = '/odometry_increments'
OBSERVATION_TOPIC = '/landmark_observations'
TRUTH_POSE_TOPIC = '/ground_truth/pose'
TRUTH_LANDMARKS_TOPIC = '/ground_truth/landmarks'


@dataclass(frozen=True)
class Replay:
    """What the processors collected from a bag, and what they warned about."""

    data: MappingData
    warnings: tuple[str, ...]
    odometry_topic: str = ODOM_TOPIC  # where the odometry came from


def replay_bag(
    path: Path, *, ingest: IngestConfig | None = None, mapper: MapperConfig | None = None
) -> Replay:
    """Run a bag's odometry (/odom or /odometry_increments) and observations through the
    nodes' processors.

    Raises:
        BagError: no /landmark_observations, no odometry topic, or too little odometry.
    """
    warnings: list[str] = []
    ingest_processor = OdometryIngest(ingest or IngestConfig(), warn=warnings.append)
    config = mapper if mapper is not None else MapperConfig(em=EmConfig())
    processor = MapperProcessor(config, warn=warnings.append)
    registry = TypeRegistry()
    with BagSource(path) as source:
        topics = source.topics()
        if OBSERVATION_TOPIC not in topics:
            raise BagError(f'bag {str(path)!r} has no {OBSERVATION_TOPIC} topic')
        odometry_topic = next((t for t in (ODOM_TOPIC, INCREMENTS_TOPIC) if t in topics), None)
        if odometry_topic is None:
            raise BagError(
                f'bag {str(path)!r} has no odometry: neither {ODOM_TOPIC} '
                f'(nav_msgs/msg/Odometry) nor {INCREMENTS_TOPIC} '
                '(slam_interfaces/msg/OdometryIncrement)'
            )
        for needed in (odometry_topic, OBSERVATION_TOPIC):
            registry.ensure(topics[needed].msgtype)
        store = registry.typestore
        for message in source.messages([odometry_topic, OBSERVATION_TOPIC]):
            decoded = store.deserialize_cdr(message.data, message.msgtype)
            if message.topic == INCREMENTS_TOPIC:
                increments = [increment_from_message(decoded)]
            elif message.topic == ODOM_TOPIC:
                increments = ingest_processor.add_odometry(*odometry_pose(decoded))
            else:  # an observation: odometry_ingest keyframes at its stamp (for /odom)
                increments = (
                    ingest_processor.add_observation_stamp(
                        stamp_to_ns(decoded.header.stamp),  # type: ignore[attr-defined]
                        seen=bool(decoded.observations),  # type: ignore[attr-defined]
                    )
                    if odometry_topic == ODOM_TOPIC
                    else []
                )
                for observation in observations_from_message(decoded):
                    processor.add_observation(observation)
            for increment in increments:
                processor.add_increment(increment)
    for increment in ingest_processor.flush():
        processor.add_increment(increment)
    if processor.num_keyframes < 2:
        raise BagError(
            f'bag {str(path)!r} holds too little odometry on {odometry_topic} to build a '
            'trajectory'
        )
    return Replay(processor.data(), tuple(warnings), odometry_topic)


@dataclass(frozen=True)
class GroundTruth:
    """True poses (T, 3) at stamps (T,) (T = 0 without /ground_truth/pose), landmark positions
    before and after the move ((L, 2) each, NaN if unknown), moveable flags, move stamp."""

    stamps_ns: IntArray
    poses: FloatArray
    landmark_ids: IntArray
    positions_before: FloatArray
    positions_after: FloatArray
    moveable: np.ndarray
    move_stamp_ns: int | None

    @property
    def has_poses(self) -> bool:
        """Whether the bag gave the robot's true poses (at least 2: there is an ATE)."""
        return len(self.stamps_ns) >= 2

    def covers(self, stamps_ns: IntArray) -> np.ndarray:
        """Return which stamps (n,) lie within the span of the true poses (none without)."""
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        if not self.has_poses:
            return np.zeros(len(stamps), dtype=bool)
        return (stamps >= self.stamps_ns[0]) & (stamps <= self.stamps_ns[-1])

    def poses_at(self, stamps_ns: IntArray) -> FloatArray:
        """Return true poses (n, 3) interpolated at ``stamps_ns``.

        Raises:
            ValueError: there are no true poses (``has_poses`` is False).
        """
        if not self.has_poses:
            raise ValueError('the ground truth has no robot poses (no /ground_truth/pose)')
        x = np.interp(stamps_ns, self.stamps_ns, self.poses[:, 0])
        y = np.interp(stamps_ns, self.stamps_ns, self.poses[:, 1])
        theta = np.interp(stamps_ns, self.stamps_ns, np.unwrap(self.poses[:, 2]))
        return np.column_stack([x, y, wrap_angle(theta)])


def read_ground_truth(path: Path) -> GroundTruth:
    """Read /ground_truth/landmarks and, if the bag has it, /ground_truth/pose.

    Raises:
        BagError: the bag has no /ground_truth/landmarks topic, or no message on it.
    """
    registry = TypeRegistry()
    stamps: list[int] = []
    poses: list[FloatArray] = []
    maps: list[Any] = []
    with BagSource(path) as source:
        topics = source.topics()
        if TRUTH_LANDMARKS_TOPIC not in topics:
            raise BagError(
                f'bag {str(path)!r} has no {TRUTH_LANDMARKS_TOPIC} topic (no ground truth)'
            )
        wanted = [t for t in (TRUTH_POSE_TOPIC, TRUTH_LANDMARKS_TOPIC) if t in topics]
        for topic in wanted:
            registry.ensure(topics[topic].msgtype)
        for message in source.messages(wanted):
            decoded = registry.typestore.deserialize_cdr(message.data, message.msgtype)
            if message.topic == TRUTH_POSE_TOPIC:
                stamp_ns, pose = odometry_pose(decoded)
                stamps.append(stamp_ns)
                poses.append(pose)
            else:
                maps.append(decoded)
    if not maps:
        raise BagError(f'bag {str(path)!r} has no message on {TRUTH_LANDMARKS_TOPIC}')
    first: Any = maps[0]
    ids = np.array([lm.landmark_id for lm in first.landmarks], dtype=np.int64)
    before = np.array([[lm.position.x, lm.position.y] for lm in first.landmarks])
    moveable = np.array([bool(lm.moveable) for lm in first.landmarks])
    after, move_stamp = before.copy(), None
    if len(maps) > 1:
        last: Any = maps[-1]
        by_id = {lm.landmark_id: lm for lm in last.landmarks}
        after = np.array([[by_id[i].position.x, by_id[i].position.y] for i in ids.tolist()])
        move_stamp = stamp_to_ns(last.header.stamp)
    return GroundTruth(
        stamps_ns=np.array(stamps, dtype=np.int64),
        poses=np.array(poses).reshape(-1, 3),
        landmark_ids=ids,
        positions_before=before,
        positions_after=after,
        moveable=moveable,
        move_stamp_ns=move_stamp,
    )


def seen_at_both_positions(data: MappingData, truth: GroundTruth) -> set[int]:
    """Return the moved landmarks observed both before and after the move (NaN: not moved)."""
    if truth.move_stamp_ns is None:
        return set()
    shift = np.abs(truth.positions_before - truth.positions_after)
    moved = truth.landmark_ids[np.any(shift > 0.0, axis=1)]  # NaN (position unknown): no
    stamps = data.obs_stamp_ns
    result = set()
    for landmark_id in moved.tolist():
        mine = stamps[data.obs_landmark_id == landmark_id]
        if np.any(mine < truth.move_stamp_ns) and np.any(mine >= truth.move_stamp_ns):
            result.add(int(landmark_id))
    return result
