"""Messages <-> em_sam_node core types. Fields are read by name, so rclpy messages and
rosbags-deserialized messages both work."""

from __future__ import annotations

from typing import Any

import numpy as np

from em_sam_node.ingest import Increment
from em_sam_node.mapper import Observation
from slam_core.arrays import FloatArray
from slam_core.geometry.quaternion import quaternion_from_yaw, yaw_from_quaternion
from slam_core.stamps import ns_to_stamp, stamp_to_ns


def yaw_from_message(q: Any) -> float:
    """Return the heading (rad) of a geometry_msgs/Quaternion (rotation about z)."""
    return yaw_from_quaternion(q.x, q.y, q.z, q.w)


def fill_yaw_quaternion(yaw: float, q: Any) -> Any:
    """Fill a geometry_msgs/Quaternion with a rotation of ``yaw`` rad about z and return it."""
    q.x, q.y, q.z, q.w = quaternion_from_yaw(yaw)
    return q


def odometry_pose(message: Any) -> tuple[int, FloatArray]:
    """Return (stamp ns, pose (x m, y m, theta rad)) of a nav_msgs/Odometry."""
    pose = message.pose.pose
    return stamp_to_ns(message.header.stamp), np.array(
        [pose.position.x, pose.position.y, yaw_from_message(pose.orientation)]
    )


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


def increment_to_message(
    increment: Increment, message: Any, *, base_frame: str, odom_frame: str
) -> Any:
    """Fill a slam_interfaces/OdometryIncrement from an Increment and return it."""
    message.header.frame_id = base_frame
    ns_to_stamp(increment.stamp_to_ns, message.header.stamp)
    ns_to_stamp(increment.stamp_from_ns, message.stamp_from)
    ns_to_stamp(increment.stamp_to_ns, message.stamp_to)
    message.forward_m, message.side_m, message.angular_rad = (float(v) for v in increment.u)
    message.covariance = [float(v) for v in increment.covariance.reshape(9)]
    message.odom_frame_id = odom_frame
    message.odom_pose_from = [float(v) for v in increment.odom_pose_from]
    message.odom_pose_to = [float(v) for v in increment.odom_pose_to]
    message.reset = bool(increment.reset)
    return message


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
