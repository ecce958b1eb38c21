"""rclpy messages of the live simulators (the bag writers build rosbags ones instead)."""

from __future__ import annotations

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import quaternion_from_yaw


def set_stamp(header: Header, stamp_ns: int, frame_id: str) -> None:
    """Set ``header`` to ``stamp_ns`` (int ns) in ``frame_id``."""
    header.stamp.sec, header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    header.frame_id = frame_id


def odometry_message(
    stamp_ns: int,
    frames: tuple[str, str],
    pose: FloatArray,
    twist: tuple[float, float],
    covariances: tuple[np.ndarray, np.ndarray],
) -> Odometry:
    """Return a planar Odometry: pose (x m, y m, theta rad), twist (m/s, rad/s), 36-vectors."""
    message = Odometry(child_frame_id=frames[1])
    set_stamp(message.header, stamp_ns, frames[0])
    position = message.pose.pose.position
    position.x, position.y = float(pose[0]), float(pose[1])
    orientation = message.pose.pose.orientation
    orientation.x, orientation.y, orientation.z, orientation.w = quaternion_from_yaw(
        float(pose[2])
    )
    message.pose.covariance = np.asarray(covariances[0], dtype=np.float64)
    message.twist.twist.linear.x, message.twist.twist.angular.z = float(twist[0]), float(twist[1])
    message.twist.covariance = np.asarray(covariances[1], dtype=np.float64)
    return message


def camera_info_message(camera: CameraModel) -> CameraInfo:
    """Return the CameraInfo of ``camera`` (no header: set it per image)."""
    fields = camera.camera_info()
    return CameraInfo(
        width=int(fields.width),
        height=int(fields.height),
        distortion_model=str(fields.distortion_model),
        d=[float(v) for v in fields.d],
        k=[float(v) for v in fields.k],
        r=[float(v) for v in fields.r],
        p=[float(v) for v in fields.p],
    )
