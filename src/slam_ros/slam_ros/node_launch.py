"""One node's launch description: standard and remap arguments (docs/design/ros_and_core.md)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Remap:
    """A topic of the node remapped by a launch argument; ``followers`` follow with a suffix."""

    topic: str
    description: str
    argument: str = ''
    followers: tuple[tuple[str, str], ...] = ()

    @property
    def name(self) -> str:
        """The launch argument's name: ``argument``, or the topic's last part."""
        return self.argument or self.topic.rsplit('/', 1)[-1]


def node_launch(package: str, executable: str, config: str, remaps: Sequence[Remap]) -> Any:
    """Return the LaunchDescription that starts ``executable`` of ``package``."""
    from launch import LaunchDescription  # type: ignore[attr-defined]  # (mypy: a launch/ folder)
    from launch.actions import DeclareLaunchArgument
    from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
    from launch_ros.actions import Node
    from launch_ros.parameter_descriptions import ParameterValue
    from launch_ros.substitutions import FindPackageShare

    default_params = PathJoinSubstitution([FindPackageShare(package), 'config', config])
    arguments = [
        DeclareLaunchArgument(
            'params_file',
            default_value=default_params,
            description=f'YAML file with the {executable} parameters',
        ),
        DeclareLaunchArgument(
            'namespace', default_value='', description='namespace of the node and its topics'
        ),
        *(
            DeclareLaunchArgument(
                remap.name, default_value=remap.topic, description=remap.description
            )
            for remap in remaps
        ),
        DeclareLaunchArgument(
            'use_sim_time',
            default_value='false',
            choices=['true', 'false'],
            description='use /clock (true when replaying a bag with its clock)',
        ),
    ]
    remappings: list[tuple[str, Any]] = []
    for remap in remaps:
        remappings.append((remap.topic, LaunchConfiguration(remap.name)))
        remappings += [
            (topic, [LaunchConfiguration(remap.name), suffix]) for topic, suffix in remap.followers
        ]
    use_sim_time = ParameterValue(LaunchConfiguration('use_sim_time'), value_type=bool)
    node = Node(
        package=package,
        executable=executable,
        name=executable,
        namespace=LaunchConfiguration('namespace'),
        parameters=[LaunchConfiguration('params_file'), {'use_sim_time': use_sim_time}],
        remappings=remappings,
        output='screen',
    )
    return LaunchDescription([*arguments, node])
