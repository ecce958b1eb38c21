"""Messages <-> em_sam_mapper: increments and sightings in, poses out. Fields are read by
name, so rclpy and rosbags messages both work."""

from __future__ import annotations

from typing import Any

import numpy as np

from em_sam_node.core.inputs import Increment, Observation
from slam_core.geometry.quaternion import quaternion_from_yaw
from slam_core.stamps import stamp_to_ns


def fill_yaw_quaternion(yaw: float, q: Any) -> Any:
    """Fill a geometry_msgs/Quaternion with a rotation of ``yaw`` rad about z and return it."""
    q.x, q.y, q.z, q.w = quaternion_from_yaw(yaw)
    return q


def observations_from_message(message: Any) -> list[Observation]:
    """Return the Observations of a slam_interfaces/LandmarkObservationArray."""
    stamp_ns = stamp_to_ns(message.header.stamp)
    return [
        Observation(
            stamp_ns=stamp_ns,
            landmark_id=int(o.landmark_id),
            z=np.array([o.range_m, o.bearing_rad], dtype=float),
            covariance=np.asarray(o.covariance, dtype=float).reshape(2, 2),
        )
        for o in message.observations
    ]


def increment_from_message(message: Any) -> Increment:
    """Return the Increment of a slam_interfaces/OdometryIncrement."""
    return Increment(
        stamp_from_ns=stamp_to_ns(message.stamp_from),
        stamp_to_ns=stamp_to_ns(message.stamp_to),
        u=np.array([message.forward_m, message.side_m, message.angular_rad], dtype=float),
        covariance=np.asarray(message.covariance, dtype=float).reshape(3, 3),
        odom_pose_from=np.asarray(message.odom_pose_from, dtype=float),
        odom_pose_to=np.asarray(message.odom_pose_to, dtype=float),
        reset=bool(message.reset),
    )
