"""Launch the shadow_filter node with its parameter file, topics remapped here.

    ros2 launch monoslam_shadow_node shadow_filter.launch.py \\
        features:=/features pose:=/camera/pose camera_info:=/camera/camera_info

The parameters come from ``config/shadow_filter.yaml`` (or ``params_file:=``); the node's
topics are relative (``features``, ``monoslam/pose``, ``camera/camera_info``,
``shadow/...``) and the input ones are remapped by the arguments below. The pose remap
applies to the default ``pose_topic`` parameter ('monoslam/pose').
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
    """Declare the arguments and the shadow_filter node."""
    default_params = PathJoinSubstitution(
        [FindPackageShare(PACKAGE), 'config', 'shadow_filter.yaml']
    )
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                'params_file',
                default_value=default_params,
                description='YAML file with the shadow_filter parameters',
            ),
            DeclareLaunchArgument(
                'namespace', default_value='', description='namespace of the node and its topics'
            ),
            DeclareLaunchArgument(
                'features',
                default_value='features',
                description='input slam_interfaces/FeatureTrackArray topic',
            ),
            DeclareLaunchArgument(
                'pose',
                default_value='monoslam/pose',
                description='input camera optical frame pose (PoseWithCovarianceStamped) topic',
            ),
            DeclareLaunchArgument(
                'camera_info',
                default_value='camera/camera_info',
                description='input sensor_msgs/CameraInfo topic',
            ),
            DeclareLaunchArgument(
                'use_sim_time',
                default_value='false',
                choices=['true', 'false'],
                description='use /clock (true when replaying a bag with its clock)',
            ),
            Node(
                package=PACKAGE,
                executable='shadow_filter',
                name='shadow_filter',
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
                    ('features', LaunchConfiguration('features')),
                    ('monoslam/pose', LaunchConfiguration('pose')),
                    ('camera/camera_info', LaunchConfiguration('camera_info')),
                ],
                output='screen',
            ),
        ]
    )
