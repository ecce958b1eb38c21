"""Launch the EM-SAM camera pipeline with managed (lifecycle) nodes, brought up in order.

    ros2 launch slam_bringup em_sam_lifecycle.launch.py
    ros2 launch slam_bringup em_sam_lifecycle.launch.py mode:=localization \\
        map_file:=out/em_sam/em_sam_map.yaml

marker_detector_lifecycle and em_sam_mapper_lifecycle start unconfigured; this file
configures each when it starts and activates it once it is inactive, as Nav2's lifecycle
manager does with autostart. A transition that fails (a bad parameter, a map file that
cannot be read) leaves the node where it was, with the reason in its log. odometry_ingest is
a plain node. Remap the camera and odometry topics onto your drivers' as for the other
launch files (graph.launch.py, peoplebot.launch.py).

Parameters: the packages' config files (marker_detector.yaml, odometry_ingest.yaml,
em_sam_mapper.yaml), then mode, map_file and report_dir from the arguments.
"""

from __future__ import annotations

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from lifecycle_msgs.msg import Transition

MANAGED = (  # package, executable, node name, config file
    ('marker_detector', 'marker_detector_lifecycle', 'marker_detector', 'marker_detector.yaml'),
    ('em_sam_node', 'em_sam_mapper_lifecycle', 'em_sam_mapper', 'em_sam_mapper.yaml'),
)


def _config(package: str, name: str) -> str:
    return str(Path(get_package_share_directory(package)) / 'config' / name)


def _brought_up(node: LifecycleNode) -> list[object]:
    """Configure ``node`` at start; activate it when it reaches inactive."""
    configure = EmitEvent(
        event=ChangeState(
            lifecycle_node_matcher=matches_action(node),
            transition_id=Transition.TRANSITION_CONFIGURE,
        )
    )
    activate = RegisterEventHandler(
        OnStateTransition(
            target_lifecycle_node=node,
            goal_state='inactive',
            entities=[
                EmitEvent(
                    event=ChangeState(
                        lifecycle_node_matcher=matches_action(node),
                        transition_id=Transition.TRANSITION_ACTIVATE,
                    )
                )
            ],
        )
    )
    return [activate, node, configure]


def generate_launch_description() -> LaunchDescription:
    arguments = [
        DeclareLaunchArgument(
            'mode', default_value='mapping', description='mapping or localization'
        ),
        DeclareLaunchArgument(
            'map_file', default_value='', description='saved map for localization'
        ),
        DeclareLaunchArgument('report_dir', default_value='out/em_sam_live'),
    ]
    mapper_overrides = {
        'mode': LaunchConfiguration('mode'),
        'map_file': LaunchConfiguration('map_file'),
        'report_dir': LaunchConfiguration('report_dir'),
    }
    actions: list[object] = [*arguments]
    for package, executable, name, config in MANAGED:
        parameters: list[object] = [_config(package, config)]
        if name == 'em_sam_mapper':
            parameters.append(mapper_overrides)
        node = LifecycleNode(
            package=package,
            executable=executable,
            name=name,
            namespace='',
            parameters=parameters,
            output='screen',
        )
        actions += _brought_up(node)
    actions.append(
        Node(
            package='em_sam_node',
            executable='odometry_ingest',
            name='odometry_ingest',
            parameters=[_config('em_sam_node', 'odometry_ingest.yaml')],
            output='screen',
        )
    )
    return LaunchDescription(actions)
