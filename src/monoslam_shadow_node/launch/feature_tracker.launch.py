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

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

PACKAGE = 'monoslam_shadow_node'


def generate_launch_description() -> LaunchDescription:
    """Declare the arguments and the feature_tracker node."""
    default_params = PathJoinSubstitution(
        [FindPackageShare(PACKAGE), 'config', 'feature_tracker.yaml']
    )
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                'params_file',
                default_value=default_params,
                description='YAML file with the feature_tracker parameters',
            ),
            DeclareLaunchArgument(
                'namespace', default_value='', description='namespace of the node and its topics'
            ),
            DeclareLaunchArgument(
                'image',
                default_value='camera/image_raw',
                description='input sensor_msgs/Image topic (CompressedImage: <image>/compressed)',
            ),
            DeclareLaunchArgument(
                'camera_info',
                default_value='camera/camera_info',
                description='input sensor_msgs/CameraInfo topic',
            ),
            DeclareLaunchArgument(
                'predictions',
                default_value='features/predicted',
                description='input predicted pixels (FeatureTrackArray), with use_predictions',
            ),
            DeclareLaunchArgument(
                'features',
                default_value='features',
                description='output slam_interfaces/FeatureTrackArray topic',
            ),
            DeclareLaunchArgument(
                'use_sim_time',
                default_value='false',
                choices=['true', 'false'],
                description='use /clock (true when replaying a bag with its clock)',
            ),
            Node(
                package=PACKAGE,
                executable='feature_tracker',
                name='feature_tracker',
                namespace=LaunchConfiguration('namespace'),
                parameters=[
                    LaunchConfiguration('params_file'),
                    {
                        'use_sim_time': ParameterValue(
                            LaunchConfiguration('use_sim_time'), value_type=bool
                        )
                    },
                ],
                remappings=[
                    ('camera/image_raw', LaunchConfiguration('image')),
                    ('camera/image_raw/compressed', [LaunchConfiguration('image'), '/compressed']),
                    ('camera/camera_info', LaunchConfiguration('camera_info')),
                    ('features/predicted', LaunchConfiguration('predictions')),
                    ('features', LaunchConfiguration('features')),
                ],
                output='screen',
            ),
        ]
    )
