"""Launch the nodes of a GRAPH file: the same graph that ``slam_run --processes`` runs.

    ros2 launch slam_bringup graph.launch.py graph:=bag_replay.yaml bag:=bags/sample \\
        record:=out/replay

The GRAPH is read and validated by ``slam_bringup.graph``; this file only maps the node
descriptions of ``slam_bringup.graph_nodes`` onto launch_ros ``Node`` actions. When the GRAPH
(or ``exit_when_player_done``) asks for it, the end of the player shuts the launch down.
"""

from __future__ import annotations

from pathlib import Path

from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
from launch_ros.actions import Node

from slam_bringup.graph import load_graph
from slam_bringup.graph_nodes import find_graph, node_descriptions, with_overrides


def _optional_path(text: str) -> Path | None:
    return Path(text).expanduser() if text else None


def _node_actions(context: LaunchContext) -> list[Node]:
    config = context.launch_configurations
    graph = with_overrides(
        load_graph(find_graph(config['graph'])),
        bag=_optional_path(config['bag']),
        rate=float(config['rate']) if config['rate'] else None,
        record=_optional_path(config['record']),
        exit_when_player_done=config['exit_when_player_done'].lower() == 'true',
    )
    actions = []
    for description in node_descriptions(graph):
        ends_launch = description.role == 'player' and graph.exit_when_player_done
        actions.append(
            Node(
                package=description.package,
                executable=description.executable,
                name=description.name,
                namespace=description.namespace or None,
                parameters=[
                    str(source) if isinstance(source, Path) else source
                    for source in description.parameters
                ],
                remappings=list(description.remappings),
                arguments=list(description.arguments),
                output='screen',
                on_exit=Shutdown(reason='the player has played the bag') if ends_launch else None,
            )
        )
    return actions


def generate_launch_description() -> LaunchDescription:
    """Declare the arguments; the nodes are made once the arguments are known."""
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                'graph',
                default_value='bag_replay.yaml',
                description="GRAPH file, or the name of one in slam_bringup's share/graphs/",
            ),
            DeclareLaunchArgument(
                'bag',
                default_value='',
                description="bag to play (replaces the GRAPH's player.bag)",
            ),
            DeclareLaunchArgument(
                'rate', default_value='', description='playback speed factor (default: GRAPH)'
            ),
            DeclareLaunchArgument(
                'record',
                default_value='',
                description="bag to record to (replaces the GRAPH's recorder.output)",
            ),
            DeclareLaunchArgument(
                'exit_when_player_done',
                default_value='false',
                choices=['true', 'false'],
                description='shut down once the player has played the bag (or as the GRAPH says)',
            ),
            OpaqueFunction(function=_node_actions),
        ]
    )
