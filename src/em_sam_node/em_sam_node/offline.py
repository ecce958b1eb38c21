"""Offline replay: a bag through the nodes' processors, and its ground truth.

``replay_bag`` feeds /odom and /landmark_observations through the same conversions and
processors (OdometryIngest, MapperProcessor) as odometry_ingest and em_sam_mapper, in bag
order, and returns the collected MappingData. ``read_ground_truth`` reads the simulator's
/ground_truth topics.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from em_sam_node.conversions import observations_from_message, odometry_pose
from em_sam_node.core.assembly import MappingData
from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.problem import FloatArray, IntArray
from em_sam_node.ingest import IngestConfig, OdometryIngest
from em_sam_node.mapper import MapperConfig, MapperProcessor
from slam_core.errors import BagError
from slam_core.geometry.se2 import wrap_angle
from slam_core.stamps import stamp_to_ns
from slam_ros.bag.source import BagSource
from slam_ros.typesys import TypeRegistry

ODOM_TOPIC = '/odom'
OBSERVATION_TOPIC = '/landmark_observations'
TRUTH_POSE_TOPIC = '/ground_truth/pose'
TRUTH_LANDMARKS_TOPIC = '/ground_truth/landmarks'


@dataclass(frozen=True)
class Replay:
    """What the processors collected from a bag, and what they warned about."""

    data: MappingData
    warnings: tuple[str, ...]


def replay_bag(path: Path, *, ingest: IngestConfig | None = None) -> Replay:
    """Run a bag's odometry and observations through the ingest and mapper processors."""
    warnings: list[str] = []
    ingest_processor = OdometryIngest(ingest or IngestConfig(), warn=warnings.append)
    mapper = MapperProcessor(MapperConfig(em=EmConfig()), warn=warnings.append)
    registry = TypeRegistry()
    with BagSource(path) as source:
        topics = source.topics()
        for needed in (ODOM_TOPIC, OBSERVATION_TOPIC):
            if needed not in topics:
                raise BagError(f'bag {str(path)!r} has no {needed} topic')
            registry.ensure(topics[needed].msgtype)
        store = registry.typestore
        for message in source.messages([ODOM_TOPIC, OBSERVATION_TOPIC]):
            decoded = store.deserialize_cdr(message.data, message.msgtype)
            if message.topic == ODOM_TOPIC:
                increments = ingest_processor.add_odometry(*odometry_pose(decoded))
            else:
                increments = ingest_processor.add_observation_stamp(
                    stamp_to_ns(decoded.header.stamp)  # type: ignore[attr-defined]
                )
                for observation in observations_from_message(decoded):
                    mapper.add_observation(observation)
            for increment in increments:
                mapper.add_increment(increment)
    for increment in ingest_processor.flush():
        mapper.add_increment(increment)
    if mapper.num_keyframes < 2:
        raise BagError(f'bag {str(path)!r} holds too little odometry to build a trajectory')
    return Replay(mapper.data(), tuple(warnings))


@dataclass(frozen=True)
class GroundTruth:
    """Simulated truth: robot poses (T,3) at stamps (T,), landmark positions before and after
    the move ((L,2) each, aligned with ``landmark_ids``), moveable flags and move stamp."""

    stamps_ns: IntArray
    poses: FloatArray
    landmark_ids: IntArray
    positions_before: FloatArray
    positions_after: FloatArray
    moveable: np.ndarray
    move_stamp_ns: int | None

    def poses_at(self, stamps_ns: IntArray) -> FloatArray:
        """Return true poses (n,3) interpolated at ``stamps_ns``."""
        x = np.interp(stamps_ns, self.stamps_ns, self.poses[:, 0])
        y = np.interp(stamps_ns, self.stamps_ns, self.poses[:, 1])
        theta = np.interp(stamps_ns, self.stamps_ns, np.unwrap(self.poses[:, 2]))
        return np.column_stack([x, y, wrap_angle(theta)])


def read_ground_truth(path: Path) -> GroundTruth:
    """Read /ground_truth/pose and /ground_truth/landmarks of a simulated bag."""
    registry = TypeRegistry()
    stamps, poses, maps = [], [], []
    with BagSource(path) as source:
        topics = source.topics()
        for needed in (TRUTH_POSE_TOPIC, TRUTH_LANDMARKS_TOPIC):
            if needed not in topics:
                raise BagError(f'bag {str(path)!r} has no {needed} topic (no ground truth)')
            registry.ensure(topics[needed].msgtype)
        for message in source.messages([TRUTH_POSE_TOPIC, TRUTH_LANDMARKS_TOPIC]):
            decoded = registry.typestore.deserialize_cdr(message.data, message.msgtype)
            if message.topic == TRUTH_POSE_TOPIC:
                stamp_ns, pose = odometry_pose(decoded)
                stamps.append(stamp_ns)
                poses.append(pose)
            else:
                maps.append(decoded)
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
        poses=np.array(poses),
        landmark_ids=ids,
        positions_before=before,
        positions_after=after,
        moveable=moveable,
        move_stamp_ns=move_stamp,
    )


def seen_at_both_positions(data: MappingData, truth: GroundTruth) -> set[int]:
    """Return the moved landmarks observed both before and after the move."""
    if truth.move_stamp_ns is None:
        return set()
    moved = truth.landmark_ids[np.any(truth.positions_before != truth.positions_after, axis=1)]
    stamps = data.obs_stamp_ns
    result = set()
    for landmark_id in moved.tolist():
        mine = stamps[data.obs_landmark_id == landmark_id]
        if np.any(mine < truth.move_stamp_ns) and np.any(mine >= truth.move_stamp_ns):
            result.add(int(landmark_id))
    return result
