"""Launch the suite live on a Peoplebot: a base driver, a camera driver, the camera mount, a
SLAM pipeline and, if asked, RViz.

    ros2 launch slam_bringup peoplebot.launch.py robot:=sim camera:=sim pipeline:=em_sam
    ros2 launch slam_bringup peoplebot.launch.py robot:=rosaria camera:=usb_cam rviz:=true

The GRAPH is the one ``peoplebot_graph`` writes for the same choices (``slam_bringup.peoplebot``:
the parts in config/peoplebot.yaml, the drivers' topics remapped onto ours), written to a
temporary file and launched by graph.launch.py; ``slam_run <that file> --processes`` runs the
same nodes without launch. RViz (rviz2, not installed by this suite) opens rviz/em_sam.rviz,
or rviz/monoslam.rviz for the monocular pipeline.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, IncludeLaunchDescription, OpaqueFunction
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch_ros.actions import Node

from slam_bringup.peoplebot import CAMERAS, PIPELINES, ROBOTS, write_graph


def _actions(context: LaunchContext) -> list[object]:
    config = context.launch_configurations
    share = Path(get_package_share_directory('slam_bringup'))
    path = Path(tempfile.mkdtemp(prefix='peoplebot-')) / 'peoplebot.yaml'
    write_graph(path, config['robot'], config['camera'], config['pipeline'])
    actions: list[object] = [
        IncludeLaunchDescription(
            PythonLaunchDescriptionSource(str(share / 'launch' / 'graph.launch.py')),
            launch_arguments={'graph': str(path)}.items(),
        )
    ]
    if config['rviz'] == 'true':
        view = 'monoslam' if config['pipeline'] == 'monoslam' else 'em_sam'
        actions.append(
            Node(
                package='rviz2',
                executable='rviz2',
                arguments=['-d', str(share / 'rviz' / f'{view}.rviz')],
                output='screen',
            )
        )
    return actions


def generate_launch_description() -> LaunchDescription:
    """Declare the arguments; the nodes are made once they are known."""
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                'robot', default_value='sim', choices=list(ROBOTS), description='base driver'
            ),
            DeclareLaunchArgument(
                'camera', default_value='sim', choices=list(CAMERAS), description='camera driver'
            ),
            DeclareLaunchArgument(
                'pipeline',
                default_value='em_sam',
                choices=list(PIPELINES),
                description='SLAM pipeline',
            ),
            DeclareLaunchArgument(
                'rviz', default_value='false', choices=['true', 'false'], description='start RViz'
            ),
            OpaqueFunction(function=_actions),
        ]
    )
