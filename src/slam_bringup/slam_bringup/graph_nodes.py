"""A GRAPH's nodes to start: overrides, descriptions, ROS arguments (docs/design/bringup.md)."""

from __future__ import annotations

import dataclasses
import difflib
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

from slam_bringup.graph_types import Graph, ParameterSource, PlayerSpec, RecorderSpec, Remapping
from slam_core.errors import GraphError

PLAYER_PLUGIN = 'slam_bringup.bag_player:BagPlayerNode'
RECORDER_PLUGIN = 'slam_bringup.bag_recorder:BagRecorderNode'


@dataclass(frozen=True)
class NodeDescription:
    """A node to start: what launch_ros ``Node`` takes, plus the in-process class (``plugin``)."""

    key: str
    role: str
    name: str
    package: str
    executable: str
    plugin: str | None
    namespace: str
    parameters: tuple[ParameterSource, ...]
    remappings: tuple[Remapping, ...]
    arguments: tuple[str, ...] = ()
    respawn: bool = False
    respawn_delay_s: float = 1.0
    respawn_parameters: dict[str, Any] | None = None

    @property
    def fully_qualified_name(self) -> str:
        """Return ``/namespace/name``."""
        return f'{self.namespace.rstrip("/")}/{self.name}'


# -- overrides and node descriptions ------------------------------------------------------
def with_overrides(
    graph: Graph,
    *,
    bag: Path | None = None,
    rate: float | None = None,
    record: Path | None = None,
    exit_when_player_done: bool = False,
    paced: bool = False,
) -> Graph:
    """Return ``graph`` with command-line overrides (``bag``, ``record`` add what is missing)."""
    player = graph.player
    if bag is not None:
        player = dataclasses.replace(player or PlayerSpec(), bag=bag)
    if rate is not None:
        if player is None:
            raise GraphError(f'graph {str(graph.path)!r} has no player, so a rate cannot be set')
        player = dataclasses.replace(player, rate=rate)
    if paced:
        if player is None:
            raise GraphError(f'graph {str(graph.path)!r} has no player, so it cannot be paced')
        player = dataclasses.replace(player, paced=True)
    recorder = graph.recorder
    if record is not None:
        recorder = dataclasses.replace(recorder or RecorderSpec(), output=record)
    return dataclasses.replace(
        graph,
        player=player,
        recorder=recorder,
        exit_when_player_done=graph.exit_when_player_done or exit_when_player_done,
    )


def _sim_time(graph: Graph) -> tuple[dict[str, Any], ...]:
    return () if graph.use_sim_time is None else ({'use_sim_time': graph.use_sim_time},)


def _player_description(graph: Graph, player: PlayerSpec) -> NodeDescription:
    if player.bag is None:
        raise graph.error('graph.player.bag', 'no bag to play; set it in the GRAPH or give --bag')
    if not player.bag.exists():
        raise graph.error('graph.player.bag', f'bag {str(player.bag)!r} does not exist')
    values: dict[str, Any] = {'bag_path': str(player.bag)}
    for field in dataclasses.fields(PlayerSpec):
        value = getattr(player, field.name)
        if field.name in ('bag', 'topics', 'remap', 'paced_nodes') or value is None or value == ():
            continue
        values[field.name] = list(value) if isinstance(value, tuple) else value
    if player.topics:
        values['topics'] = list(player.topics)
    if player.remap:
        values['remap'] = [f'{source}:={target}' for source, target in player.remap]
    if player.paced_nodes:
        values['paced_nodes'] = list(player.paced_nodes)
    return NodeDescription(
        key='graph.player',
        role='player',
        name='bag_player',
        package='slam_bringup',
        executable='bag_player',
        plugin=PLAYER_PLUGIN,
        namespace='',
        parameters=(values, *_sim_time(graph)),
        remappings=(),
    )


def _recorder_description(graph: Graph, recorder: RecorderSpec) -> NodeDescription:
    values: dict[str, Any] = {}
    if recorder.output is not None:
        if Path(recorder.output).expanduser().exists():  # checked before any node starts
            raise graph.error(
                'graph.recorder.output',
                f'{str(recorder.output)!r} exists already (a recording is never overwritten); '
                'remove it or record elsewhere with --record PATH',
            )
        values['output'] = str(recorder.output)
    if recorder.topics:
        values['topics'] = list(recorder.topics)
    if recorder.exclude:
        values['exclude'] = list(recorder.exclude)
    for name in ('discovery_period_s', 'queue_depth', 'flush_period_s'):
        if getattr(recorder, name) is not None:
            values[name] = getattr(recorder, name)
    # bag_recorder's command line wants the topics, or --all.
    arguments = recorder.topics or ('--all',)
    return NodeDescription(
        key='graph.recorder',
        role='recorder',
        name='bag_recorder',
        package='slam_bringup',
        executable='bag_recorder',
        plugin=RECORDER_PLUGIN,
        namespace='',
        parameters=(*((values,) if values else ()), *_sim_time(graph)),
        remappings=(),
        arguments=tuple(arguments),
    )


def node_descriptions(graph: Graph) -> tuple[NodeDescription, ...]:
    """Return the nodes to start, in order (nodes, player, recorder); raises GraphError."""
    if graph.exit_when_player_done and graph.player is None:
        raise graph.error('graph.exit_when_player_done', 'is set but the graph has no player')
    descriptions = [
        NodeDescription(
            key=node.key,
            role='node',
            name=node.name,
            package=node.package,
            executable=node.executable,
            plugin=node.plugin,
            namespace=node.namespace,
            parameters=(*node.parameters, *_sim_time(graph)),
            remappings=node.remappings,
            respawn=node.respawn,
            respawn_delay_s=node.respawn_delay_s,
            respawn_parameters=node.respawn_parameters,
        )
        for node in graph.nodes
    ]
    if graph.player is not None:
        player = _player_description(graph, graph.player)
        if graph.player.paced:  # the player waits for the graph's nodes to report
            names = [d.fully_qualified_name for d in descriptions]
            player = dataclasses.replace(
                player, parameters=(*player.parameters, {'paced_nodes': names})
            )
        descriptions.append(player)
    if graph.recorder is not None:
        descriptions.append(_recorder_description(graph, graph.recorder))
    return tuple(descriptions)


def write_parameter_file(values: Mapping[str, Any], path: Path) -> Path:
    """Write inline parameters as a ``/**: ros__parameters:`` YAML file; return ``path``."""
    path.write_text(
        yaml.safe_dump({'/**': {'ros__parameters': dict(values)}}, sort_keys=False),
        encoding='utf-8',
    )
    return path


def ros_arguments(description: NodeDescription, scratch_dir: Path) -> list[str]:
    """Return a node's ``--ros-args``; inline parameters become files in ``scratch_dir``."""
    arguments = ['--ros-args', '-r', f'__node:={description.name}']
    if description.namespace:
        arguments += ['-r', f'__ns:={description.namespace}']
    stem = description.fully_qualified_name.strip('/').replace('/', '.')
    for index, parameters in enumerate(description.parameters):
        if isinstance(parameters, dict):
            parameters = write_parameter_file(parameters, scratch_dir / f'{stem}.{index}.yaml')
        arguments += ['--params-file', str(parameters)]
    for source, target in description.remappings:
        arguments += ['-r', f'{source}:={target}']
    return arguments


def bundled_graphs_dir() -> Path | None:
    """slam_bringup's installed graphs/ directory, or None when the package is not found."""
    try:
        return Path(get_package_share_directory('slam_bringup')) / 'graphs'
    except (PackageNotFoundError, ValueError):
        return None


def bundled_graphs() -> dict[str, str]:
    """``{name: description}`` of the bundled GRAPH files (their ``graph.description``)."""
    share = bundled_graphs_dir()
    graphs: dict[str, str] = {}
    for path in sorted(share.glob('*.yaml')) if share is not None else []:
        try:
            document = yaml.safe_load(path.read_text(encoding='utf-8'))
            description = str(document['graph'].get('description', ''))
        except (OSError, yaml.YAMLError, KeyError, TypeError, AttributeError):
            description = '(unreadable)'
        graphs[path.name] = description
    return graphs


def bundled_graphs_help() -> str:
    """The bundled GRAPH files, one line each, for ``slam_run --help``."""
    lines = [f'  {name:<36} {text}' for name, text in bundled_graphs().items()]
    return 'bundled graphs (give the name alone):\n' + '\n'.join(lines)


def find_graph(text: str) -> Path:
    """Return the GRAPH file ``text`` (a path or a bundled name); GraphError names close ones."""
    path = Path(text).expanduser()
    if path.exists() or os.sep in text:
        return path
    share = bundled_graphs_dir()
    if share is None:
        return path
    for candidate in (share / text, share / f'{text}.yaml'):
        if candidate.is_file():
            return candidate
    names = sorted(p.name for p in share.glob('*.yaml'))
    close = difflib.get_close_matches(text if text.endswith('.yaml') else f'{text}.yaml', names)
    hint = f'; did you mean {" or ".join(repr(c) for c in close[:2])}?' if close else ''
    raise GraphError(
        f'graph {text!r} is neither a file nor a bundled graph{hint} (bundled: '
        f'{", ".join(names)}; `slam_run --help` describes each)'
    )
