"""Launch the shadow_filter node with its parameter file, topics remapped here.

    ros2 launch monoslam_shadow_node shadow_filter.launch.py \\
        features:=/features pose:=/camera/pose camera_info:=/camera/camera_info

The parameters come from ``config/shadow_filter.yaml`` (or ``params_file:=``); the node's
topics are relative (``features``, ``monoslam/pose``, ``camera/camera_info``,
``shadow/...``) and the input ones are remapped by the arguments below. The pose remap
applies to the default ``pose_topic`` parameter ('monoslam/pose').
"""

from __future__ import annotations

from slam_ros.node_launch import Remap, node_launch


def generate_launch_description():
    """Declare the arguments and the shadow_filter node."""
    return node_launch(
        'monoslam_shadow_node',
        'shadow_filter',
        'shadow_filter.yaml',
        [
            Remap('features', 'input slam_interfaces/FeatureTrackArray topic'),
            Remap(
                'monoslam/pose',
                'input camera optical frame pose (PoseWithCovarianceStamped) topic',
                argument='pose',
            ),
            Remap('camera/camera_info', 'input sensor_msgs/CameraInfo topic'),
        ],
    )
