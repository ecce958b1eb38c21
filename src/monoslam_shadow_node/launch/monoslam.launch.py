"""Launch the monoslam node with its parameter file, topics remapped here.

    ros2 launch monoslam_shadow_node monoslam.launch.py \\
        features:=/features fiducials:=/fiducials camera_info:=/camera/camera_info

The parameters come from ``config/monoslam.yaml`` (or ``params_file:=``; a file that sets only
some parameters leaves the others at their defaults, e.g. the simulated scene's
``config/monoslam_dynamic_camera.yaml``, which places the initialization target). The node's
topics are relative (``features``, ``fiducials``, ``camera/camera_info``,
``shadow/static_features``, ``features/predicted``, ``monoslam/...``); the inputs and the
predictions are remapped by the arguments below.
"""

from __future__ import annotations

from slam_ros.node_launch import Remap, node_launch


def generate_launch_description():
    """Declare the arguments and the monoslam node."""
    return node_launch(
        'monoslam_shadow_node',
        'monoslam',
        'monoslam.yaml',
        [
            Remap('features', 'input slam_interfaces/FeatureTrackArray topic'),
            Remap('fiducials', 'input slam_interfaces/FiducialArray topic (the target)'),
            Remap('camera/camera_info', 'input sensor_msgs/CameraInfo topic'),
            Remap(
                'shadow/static_features',
                'input handovers (ShadowTrackArray) from the Shadow filter',
            ),
            Remap(
                'features/predicted',
                'output predicted pixels (FeatureTrackArray), if enabled',
                argument='predictions',
            ),
        ],
    )
