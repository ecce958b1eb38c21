"""The inputs of the mapper: odometry increments between keyframes and range-bearing
sightings."""

from __future__ import annotations

from dataclasses import dataclass

from slam_core.arrays import FloatArray


@dataclass(frozen=True)
class Increment:
    """Motion between two keyframes (eq. 2): u = (u0 m, u1 m, u2 rad), covariance (3,3).

    ``odom_pose_from``/``odom_pose_to`` are the keyframes' poses in the odometry frame
    (x m, y m, theta rad); ``reset`` marks a zero-motion bridge over an odometry reset.
    """

    stamp_from_ns: int
    stamp_to_ns: int
    u: FloatArray
    covariance: FloatArray
    odom_pose_from: FloatArray
    odom_pose_to: FloatArray
    reset: bool = False


@dataclass(frozen=True)
class Observation:
    """One range-bearing sighting: stamp int ns, landmark id, (range m, bearing rad), (2,2)."""

    stamp_ns: int
    landmark_id: int
    z: FloatArray
    covariance: FloatArray
