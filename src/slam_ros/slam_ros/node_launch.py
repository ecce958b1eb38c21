"""One node's launch description from its topics: the ``params_file``, ``namespace`` and
``use_sim_time`` arguments every node takes, and one argument per remappable topic.

    def generate_launch_description():
        return node_launch('monoslam_shadow_node', 'monoslam', 'monoslam.yaml', [
            Remap('features', 'input slam_interfaces/FeatureTrackArray topic'),
        ])
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Remap:
    """A topic of the node (relative, as it names it) that an argument of the same name
    remaps, unless ``argument`` names it otherwise; ``followers`` are topics that follow it
    with a suffix (``('camera/image_raw/compressed', '/compressed')``: image_transport's
    compressed topic beside the raw one)."""

    topic: str
    description: str
    argument: str = ''
    followers: tuple[tuple[str, str], ...] = ()

    @property
    def name(self) -> str:
        """The launch argument's name: ``argument``, or the topic's last part."""
        return self.argument or self.topic.rsplit('/', 1)[-1]


def node_launch(package: str, executable: str, config: str, remaps: Sequence[Remap]) -> Any:
    """Return the LaunchDescription that starts ``executable`` of ``package`` (named as the
    executable) with ``config/<config>`` of the package's share directory (or
    ``params_file:=``), its ``remaps`` from their arguments, in ``namespace:=``, on /clock
    with ``use_sim_time:=true``."""
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
