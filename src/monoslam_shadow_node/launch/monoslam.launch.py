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

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

PACKAGE = 'monoslam_shadow_node'


def generate_launch_description() -> LaunchDescription:
    """Declare the arguments and the monoslam node."""
    default_params = PathJoinSubstitution([FindPackageShare(PACKAGE), 'config', 'monoslam.yaml'])
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                'params_file',
                default_value=default_params,
                description='YAML file with the monoslam parameters',
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
                'fiducials',
                default_value='fiducials',
                description='input slam_interfaces/FiducialArray topic (the target)',
            ),
            DeclareLaunchArgument(
                'camera_info',
                default_value='camera/camera_info',
                description='input sensor_msgs/CameraInfo topic',
            ),
            DeclareLaunchArgument(
                'static_features',
                default_value='shadow/static_features',
                description='input handovers (ShadowTrackArray) from the Shadow filter',
            ),
            DeclareLaunchArgument(
                'predictions',
                default_value='features/predicted',
                description='output predicted pixels (FeatureTrackArray), if enabled',
            ),
            DeclareLaunchArgument(
                'use_sim_time',
                default_value='false',
                choices=['true', 'false'],
                description='use /clock (true when replaying a bag with its clock)',
            ),
            Node(
                package=PACKAGE,
                executable='monoslam',
                name='monoslam',
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
                    ('fiducials', LaunchConfiguration('fiducials')),
                    ('camera/camera_info', LaunchConfiguration('camera_info')),
                    ('shadow/static_features', LaunchConfiguration('static_features')),
                    ('features/predicted', LaunchConfiguration('predictions')),
                ],
                output='screen',
            ),
        ]
    )
