"""Launch the feature_tracker node with its parameter file, topics remapped here.

    ros2 launch monoslam_shadow_node feature_tracker.launch.py \\
        image:=/camera/image_raw camera_info:=/camera/camera_info features:=/features

The parameters come from ``config/feature_tracker.yaml`` (or ``params_file:=``); the node's
topics are relative (``camera/image_raw``, ``camera/image_raw/compressed``,
``camera/camera_info``, ``features/predicted``, ``features``) and remapped by the arguments
below. The compressed topic follows the image topic (``<image>/compressed``), as
image_transport names it; which one is used is the ``image_transport`` parameter.
"""

from __future__ import annotations

from slam_ros.node_launch import Remap, node_launch


def generate_launch_description():
    """Declare the arguments and the feature_tracker node."""
    return node_launch(
        'monoslam_shadow_node',
        'feature_tracker',
        'feature_tracker.yaml',
        [
            Remap(
                'camera/image_raw',
                'input sensor_msgs/Image topic (CompressedImage: <image>/compressed)',
                argument='image',
                followers=(('camera/image_raw/compressed', '/compressed'),),
            ),
            Remap('camera/camera_info', 'input sensor_msgs/CameraInfo topic'),
            Remap(
                'features/predicted',
                'input predicted pixels (FeatureTrackArray), with use_predictions',
                argument='predictions',
            ),
            Remap('features', 'output slam_interfaces/FeatureTrackArray topic'),
        ],
    )
