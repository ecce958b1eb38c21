"""camera_mount: publishes base_frame -> camera_frame -> optical_frame on /tf_static, latched."""

from __future__ import annotations

import math
import sys
from typing import Any

from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from tf2_msgs.msg import TFMessage

from slam_core.cli import console_main
from slam_core.geometry.quaternion import quaternion_from_rotation
from slam_core.geometry.se3 import OPTICAL_IN_LINK
from slam_core.geometry.so3 import rotation_from_rpy
from slam_core.params import Param, ParamTable
from slam_ros.params import declare_parameters
from slam_ros.qos import latched_qos
from slam_ros.spin import spin_node


def _finite(values: Any) -> str | None:
    return None if all(math.isfinite(float(v)) for v in values) else 'must be finite'


PARAMETERS = ParamTable(
    'camera_mount',
    (
        Param('base_frame', 'base_link', 'robot base frame id'),
        Param('camera_frame', 'camera_link', 'camera body frame id (x forward, z up)'),
        Param('optical_frame', 'camera_optical_frame', 'camera optical frame id (REP 103)'),
        Param(
            'xyz_m',
            [0.1, 0.0, 1.0],
            'camera_frame origin in base_frame, m',
            length=3,
            validator=_finite,
        ),
        Param(
            'rpy_rad',
            [0.0, 0.0, 0.0],
            'camera_frame roll, pitch, yaw in base_frame, rad',
            length=3,
            validator=_finite,
        ),
    ),
)


def mount_transforms(values: dict[str, Any], stamp: Any) -> list[TransformStamped]:
    """Return base -> camera and camera -> optical for validated parameter ``values``."""
    rotation = rotation_from_rpy(*(float(v) for v in values['rpy_rad']))
    links = (
        (values['base_frame'], values['camera_frame'], rotation, values['xyz_m']),
        (values['camera_frame'], values['optical_frame'], OPTICAL_IN_LINK, (0.0, 0.0, 0.0)),
    )
    transforms = []
    for parent, child, matrix, xyz in links:
        transform = TransformStamped(child_frame_id=str(child))
        transform.header.stamp, transform.header.frame_id = stamp, str(parent)
        translation = transform.transform.translation
        translation.x, translation.y, translation.z = (float(v) for v in xyz)
        w, x, y, z = quaternion_from_rotation(matrix).tolist()
        rotation_msg = transform.transform.rotation
        rotation_msg.x, rotation_msg.y, rotation_msg.z, rotation_msg.w = x, y, z, w
        transforms.append(transform)
    return transforms


class CameraMountNode(Node):
    """Publishes the camera mount once, latched."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('camera_mount', **kwargs)
        values = declare_parameters(self, PARAMETERS)
        frames = [values['base_frame'], values['camera_frame'], values['optical_frame']]
        if len(set(frames)) != 3 or not all(frames):
            raise ValueError(
                f'camera_mount: base_frame, camera_frame and optical_frame must be three '
                f'different non-empty names, got {frames}'
            )
        self.publisher = self.create_publisher(TFMessage, '/tf_static', latched_qos())
        transforms = mount_transforms(values, self.get_clock().now().to_msg())
        self.publisher.publish(TFMessage(transforms=transforms))
        x, y, z = (float(v) for v in values['xyz_m'])
        self.get_logger().info(
            f'camera_mount: {frames[0]} -> {frames[1]} at ({x:g}, {y:g}, {z:g}) m, rpy '
            f'{[float(v) for v in values["rpy_rad"]]} rad -> {frames[2]} on /tf_static'
        )


@console_main('camera_mount')
def main(argv: list[str] | None = None) -> int:
    """Publish the mount and keep it latched until Ctrl-C."""
    return spin_node('camera_mount', CameraMountNode, argv, parameters=PARAMETERS, doc=__doc__)


if __name__ == '__main__':
    sys.exit(main())
