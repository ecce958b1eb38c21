"""Messages <-> odometry_ingest: nav_msgs/Odometry in, slam_interfaces/OdometryIncrement
out. Fields are read by name, so rclpy and rosbags messages both work."""

from __future__ import annotations

from typing import Any

import numpy as np

from em_sam_node.core.inputs import Increment
from slam_core.arrays import FloatArray
from slam_core.geometry.quaternion import yaw_from_quaternion
from slam_core.stamps import ns_to_stamp, stamp_to_ns


def yaw_from_message(q: Any) -> float:
    """Return the heading (rad) of a geometry_msgs/Quaternion (rotation about z)."""
    return yaw_from_quaternion(q.x, q.y, q.z, q.w)


def odometry_pose(message: Any) -> tuple[int, FloatArray]:
    """Return (stamp ns, pose (x m, y m, theta rad)) of a nav_msgs/Odometry."""
    pose = message.pose.pose
    return stamp_to_ns(message.header.stamp), np.array(
        [pose.position.x, pose.position.y, yaw_from_message(pose.orientation)]
    )


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
