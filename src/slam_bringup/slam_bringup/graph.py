"""GRAPH files: read and validate the YAML node graph of slam_run (docs/design/bringup.md)."""

from __future__ import annotations

import difflib
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml
from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

from slam_bringup.graph_params import check_graph_parameters
from slam_bringup.graph_types import (
    Graph,
    NodeSpec,
    ParameterSource,
    PlayerSpec,
    RecorderSpec,
    Remapping,
    graph_error,
)
from slam_core.errors import GraphError

PACKAGE_SCHEME = 'package://'
_NAME = re.compile(r'[A-Za-z_][A-Za-z0-9_]*')
_PACKAGE = re.compile(r'[A-Za-z][A-Za-z0-9_]*')
_PLUGIN = re.compile(r'[A-Za-z_][A-Za-z0-9_.]*:[A-Za-z_][A-Za-z0-9_]*')
_NAMESPACE = re.compile(r'/?([A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*)?')
_TOPIC = re.compile(r'[~/A-Za-z_{][A-Za-z0-9_/{}~]*')
_PARAMETER = re.compile(r'[A-Za-z_][A-Za-z0-9_.]*')


# -- YAML ---------------------------------------------------------------------------------
class _UniqueKeyLoader(yaml.SafeLoader):
    """A SafeLoader that rejects duplicate mapping keys instead of keeping the last one."""


def _construct_unique_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode) -> Any:
    seen: set[object] = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node)
        if isinstance(key, str | int | float | bool) and key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f'duplicate key {key!r}', key_node.start_mark
            )
        seen.add(key)
    return loader.construct_mapping(node)


_UniqueKeyLoader.add_constructor(
    yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
    _construct_unique_mapping,
)


def read_yaml(path: Path, label: str) -> Any:
    """Parse a YAML file; raise GraphError ``<label>: ...`` naming the line of a syntax error."""
    try:
        text = path.read_text(encoding='utf-8')
    except FileNotFoundError:
        raise GraphError(f'{label} does not exist') from None
    except (OSError, UnicodeDecodeError) as err:
        raise GraphError(f'{label} cannot be read: {err}') from None
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        where = f'line {mark.line + 1}, column {mark.column + 1}: ' if mark else ''
        problem = err.problem or err.context or 'invalid YAML'
        raise GraphError(f'{label}: {where}YAML syntax error: {problem}') from None
    except yaml.YAMLError as err:
        raise GraphError(f'{label}: YAML error: {err}') from None


# -- validation helpers -------------------------------------------------------------------
class _Checker:
    """Type and key checks that raise GraphError naming the file and the key path."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def error(self, key: str, message: str) -> GraphError:
        return graph_error(self.path, key, message)

    def mapping(
        self, value: object, key: str, required: tuple[str, ...], optional: tuple[str, ...]
    ) -> dict[str, Any]:
        """Check a mapping's keys; ``key`` is its path, '' for the top level of the file."""
        if not isinstance(value, dict):
            raise self.error(key or 'top level', f'must be a mapping, got {_describe(value)}')
        allowed = (*required, *optional)
        for name in value:
            if name not in allowed:
                close = difflib.get_close_matches(str(name), allowed, n=1)
                hint = f"did you mean '{close[0]}'? " if close else ''
                raise self.error(
                    _join(key, name), f'unknown key; {hint}allowed keys: {", ".join(allowed)}'
                )
        for name in required:
            if name not in value:
                raise self.error(_join(key, name), 'missing required key')
        return value

    def string(self, value: object, key: str, pattern: re.Pattern[str] | None = None) -> str:
        if not isinstance(value, str):
            raise self.error(key, f'must be a string, got {_describe(value)}')
        if pattern is not None and not pattern.fullmatch(value):
            raise self.error(key, f'{value!r} is not a valid name (pattern {pattern.pattern})')
        return value

    def boolean(self, value: object, key: str) -> bool:
        if not isinstance(value, bool):
            raise self.error(key, f'must be true or false, got {_describe(value)}')
        return value

    def number(self, value: object, key: str, *, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(key, f'must be a number, got {_describe(value)}')
        if value != value or value < 0 or (positive and value == 0):  # NaN fails the first
            raise self.error(key, f'{value!r} must be {"> 0" if positive else ">= 0"}')
        return float(value)

    def positive(self, value: object, key: str) -> float:
        return self.number(value, key, positive=True)

    def integer(self, value: object, key: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise self.error(key, f'must be an integer >= 1, got {_describe(value)}')
        return value

    def strings(self, value: object, key: str) -> tuple[str, ...]:
        if not isinstance(value, list):
            raise self.error(key, f'must be a list of strings, got {_describe(value)}')
        return tuple(self.string(item, f'{key}[{i}]', _TOPIC) for i, item in enumerate(value))

    def remappings(self, value: object, key: str) -> tuple[Remapping, ...]:
        """Accept ``{from: to}`` or ``['from:=to']``; reject bad names and repeated sources."""
        pairs: list[tuple[str, object, object]] = []
        if isinstance(value, dict):
            pairs = [(f'{key}.{source}', source, target) for source, target in value.items()]
        elif isinstance(value, list):
            for index, entry in enumerate(value):
                where = f'{key}[{index}]'
                text = self.string(entry, where)
                source, sep, target = text.partition(':=')
                if not sep:
                    raise self.error(where, f"{text!r} is not of the form 'from:=to'")
                pairs.append((where, source.strip(), target.strip()))
        else:
            raise self.error(
                key,
                f"must be a mapping {{from: to}} or a list of 'from:=to', got {_describe(value)}",
            )
        remaps: dict[str, str] = {}
        for where, raw_source, raw_target in pairs:
            names = [self._topic(name, where) for name in (raw_source, raw_target)]
            if names[0].startswith('__'):
                raise self.error(where, f'set {names[0]!r} with the name and namespace keys')
            if names[0] in remaps:
                raise self.error(where, f'{names[0]!r} is remapped twice')
            remaps[names[0]] = names[1]
        return tuple(remaps.items())

    def _topic(self, name: object, key: str) -> str:
        if not isinstance(name, str) or not _TOPIC.fullmatch(name):
            raise self.error(key, f'{name!r} is not a valid topic or service name')
        return name

    def path_relative(self, value: object, key: str) -> Path:
        """Resolve ``package://<pkg>/<path>`` in that package's share, else from the GRAPH."""
        text = self.string(value, key)
        if not text:
            raise self.error(key, 'must not be empty')
        if text.startswith(PACKAGE_SCHEME):
            package, _, relative = text[len(PACKAGE_SCHEME) :].partition('/')
            try:
                return Path(get_package_share_directory(package)) / relative
            except (PackageNotFoundError, ValueError):
                raise self.error(
                    key,
                    f'package {package!r} of {text!r} is not installed (not on '
                    'AMENT_PREFIX_PATH); build the workspace and source scripts/env.sh',
                ) from None
        path = Path(text).expanduser()
        return path if path.is_absolute() else self.path.parent / path


def _join(key: str, name: object) -> str:
    return f'{key}.{name}' if key else str(name)


def _describe(value: object) -> str:
    if value is None:
        return 'nothing (null)'
    return f'{type(value).__name__} {value!r}'


# -- sections -----------------------------------------------------------------------------
_NODE_REQUIRED = ('name', 'package', 'executable')
_NODE_OPTIONAL = (
    'plugin',
    'namespace',
    'parameters',
    'remappings',
    'respawn',
    'respawn_delay_s',
    'respawn_parameters',
)
_PLAYER_KEYS = (
    'bag',
    'rate',
    'start_offset_s',
    'topics',
    'remap',
    'replayable_topics',
    'loop',
    'clock_hz',
    'wait_for_subscribers_s',
    'progress_period_s',
    'paced',
    'paced_nodes',
    'paced_timeout_s',
)
_RECORDER_KEYS = (
    'output',
    'topics',
    'exclude',
    'discovery_period_s',
    'queue_depth',
    'flush_period_s',
)
_GRAPH_KEYS = (
    'description',
    'nodes',
    'player',
    'recorder',
    'use_sim_time',
    'exit_when_player_done',
)


def _namespace(check: _Checker, value: object, key: str) -> str:
    text = check.string(value, key).strip()
    if not _NAMESPACE.fullmatch(text):
        raise check.error(key, f'{text!r} is not a valid namespace (like robot1 or /robot1)')
    return '/' + text.strip('/') if text.strip('/') else ''


def _parameter_file(check: _Checker, value: object, key: str) -> Path:
    path = check.path_relative(value, key)
    if not path.is_file():
        looked = '' if str(path) == value else f' (looked for {str(path)!r})'
        raise check.error(key, f'file {value!r} does not exist{looked}')
    content = read_yaml(path, f'graph {str(check.path)!r}: {key}: file {str(path)!r}')
    if not _has_ros_parameters(content):
        raise check.error(
            key,
            f"file {str(path)!r} has no 'ros__parameters' key; parameter files look like "
            "'/**: {ros__parameters: {name: value}}'",
        )
    return path


def _has_ros_parameters(content: object) -> bool:
    if not isinstance(content, dict):
        return False
    return 'ros__parameters' in content or any(_has_ros_parameters(v) for v in content.values())


def _parameter_value(check: _Checker, value: object, key: str) -> None:
    scalar = {bool, int, float, str}
    if isinstance(value, dict):
        _inline_parameters(check, value, key)
    elif isinstance(value, list):
        if not value:
            raise check.error(key, 'an empty list has no ROS parameter type; leave it out')
        kinds = {type(item) for item in value}  # bool is not int here
        if len(kinds) > 1 or not kinds <= scalar:
            raise check.error(
                key,
                f'a list must hold values of one type (bool, int, float or string; '
                f'write 1.0 for a float), got {value!r}',
            )
    elif type(value) not in scalar:
        raise check.error(
            key, f'must be a bool, number, string, list or mapping, got {_describe(value)}'
        )


def _inline_parameters(check: _Checker, value: dict[Any, Any], key: str) -> dict[str, Any]:
    for name, item in value.items():
        if not isinstance(name, str) or not _PARAMETER.fullmatch(name):
            raise check.error(f'{key}.{name}', 'is not a valid parameter name')
        _parameter_value(check, item, f'{key}.{name}')
    return value


def _node(check: _Checker, value: object, key: str) -> NodeSpec:
    entry = check.mapping(value, key, _NODE_REQUIRED, _NODE_OPTIONAL)
    plugin = entry.get('plugin')
    parameters: list[ParameterSource] = []
    raw_parameters = entry.get('parameters', [])
    if not isinstance(raw_parameters, list):
        raise check.error(
            f'{key}.parameters',
            f'must be a list of files and mappings, got {_describe(raw_parameters)}',
        )
    for index, item in enumerate(raw_parameters):
        where = f'{key}.parameters[{index}]'
        if isinstance(item, dict):
            parameters.append(_inline_parameters(check, item, where))
        else:
            parameters.append(_parameter_file(check, item, where))
    return NodeSpec(
        key=key,
        name=check.string(entry['name'], f'{key}.name', _NAME),
        package=check.string(entry['package'], f'{key}.package', _PACKAGE),
        executable=check.string(entry['executable'], f'{key}.executable', _NAME),
        plugin=None if plugin is None else check.string(plugin, f'{key}.plugin', _PLUGIN),
        namespace=_namespace(check, entry.get('namespace', ''), f'{key}.namespace'),
        parameters=tuple(parameters),
        remappings=check.remappings(entry.get('remappings', {}), f'{key}.remappings'),
        **_respawn(check, entry, key),
    )


def _respawn(check: _Checker, entry: dict[str, Any], key: str) -> dict[str, Any]:
    respawn = bool(_optional(entry, 'respawn', check.boolean, key))
    for name in ('respawn_delay_s', 'respawn_parameters'):
        if name in entry and not respawn:
            raise check.error(f'{key}.{name}', 'is set but respawn is not true')
    extra = entry.get('respawn_parameters')
    if extra is not None and not isinstance(extra, dict):
        raise check.error(
            f'{key}.respawn_parameters', f'must be a mapping, got {_describe(extra)}'
        )
    return {
        'respawn': respawn,
        'respawn_delay_s': _optional(entry, 'respawn_delay_s', check.positive, key) or 1.0,
        'respawn_parameters': None
        if extra is None
        else _inline_parameters(check, extra, f'{key}.respawn_parameters'),
    }


def _optional(
    entry: dict[str, Any], name: str, convert: Callable[[object, str], Any], key: str
) -> Any:
    return convert(entry[name], f'{key}.{name}') if name in entry else None


def _player(check: _Checker, value: object, key: str) -> PlayerSpec:
    entry = check.mapping(value, key, (), _PLAYER_KEYS)
    positive = check.positive
    return PlayerSpec(
        bag=_optional(entry, 'bag', check.path_relative, key),
        rate=_optional(entry, 'rate', positive, key),
        start_offset_s=_optional(entry, 'start_offset_s', check.number, key),
        topics=_optional(entry, 'topics', check.strings, key) or (),
        remap=_optional(entry, 'remap', check.remappings, key) or (),
        replayable_topics=_optional(entry, 'replayable_topics', check.strings, key) or (),
        loop=_optional(entry, 'loop', check.boolean, key),
        clock_hz=_optional(entry, 'clock_hz', check.number, key),
        wait_for_subscribers_s=_optional(entry, 'wait_for_subscribers_s', check.number, key),
        progress_period_s=_optional(entry, 'progress_period_s', positive, key),
        paced=_optional(entry, 'paced', check.boolean, key),
        paced_nodes=_optional(entry, 'paced_nodes', check.strings, key) or (),
        paced_timeout_s=_optional(entry, 'paced_timeout_s', positive, key),
    )


def _recorder(check: _Checker, value: object, key: str) -> RecorderSpec:
    entry = check.mapping(value, key, (), _RECORDER_KEYS)
    output = _optional(entry, 'output', check.string, key)
    if output == '':
        raise check.error(f'{key}.output', 'must not be empty; leave it out for the default')
    return RecorderSpec(
        output=None if output is None else Path(output).expanduser(),
        topics=_optional(entry, 'topics', check.strings, key) or (),
        exclude=_optional(entry, 'exclude', check.strings, key),
        discovery_period_s=_optional(entry, 'discovery_period_s', check.positive, key),
        queue_depth=_optional(entry, 'queue_depth', check.integer, key),
        flush_period_s=_optional(entry, 'flush_period_s', check.positive, key),
    )


def load_graph(path: Path | str) -> Graph:
    """Read and validate a GRAPH file (raises GraphError naming the file and the key)."""
    path = Path(path)
    check = _Checker(path)
    content = read_yaml(path, f'graph {str(path)!r}')
    if content is None:
        raise GraphError(f"graph {str(path)!r} is empty; it needs a 'graph' mapping")
    root = check.mapping(content, '', ('graph',), ())
    if root['graph'] is None:
        root['graph'] = {}
    entry = check.mapping(root['graph'], 'graph', (), _GRAPH_KEYS)
    raw_nodes = entry.get('nodes') or []
    if not isinstance(raw_nodes, list):
        raise check.error('graph.nodes', f'must be a list, got {_describe(raw_nodes)}')
    nodes = tuple(_node(check, item, f'graph.nodes[{i}]') for i, item in enumerate(raw_nodes))
    player = (
        None if entry.get('player') is None else _player(check, entry['player'], 'graph.player')
    )
    recorder = entry.get('recorder')
    graph = Graph(
        path=path,
        description=check.string(entry.get('description', ''), 'graph.description'),
        nodes=nodes,
        player=player,
        recorder=None if recorder is None else _recorder(check, recorder, 'graph.recorder'),
        use_sim_time=_optional(entry, 'use_sim_time', check.boolean, 'graph'),
        exit_when_player_done=bool(
            _optional(entry, 'exit_when_player_done', check.boolean, 'graph')
        ),
    )
    _check_unique_names(graph)
    check_graph_parameters(graph)
    return graph


def _check_unique_names(graph: Graph) -> None:
    seen: dict[str, str] = {}
    if graph.player is not None:
        seen['/bag_player'] = 'graph.player'
    if graph.recorder is not None:
        seen['/bag_recorder'] = 'graph.recorder'
    for node in graph.nodes:
        name = f'{node.namespace}/{node.name}'
        if name in seen:
            raise graph.error(f'{node.key}.name', f'node {name!r} is also {seen[name]}')
        seen[name] = node.key
