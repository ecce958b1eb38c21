"""GRAPH parameter checks: a node's GRAPH parameters must be declared (docs/design/bringup.md)."""

from __future__ import annotations

import importlib
import importlib.metadata
from pathlib import Path
from typing import Any

import yaml

from slam_bringup.graph_types import Graph, NodeSpec
from slam_core.errors import ParameterError
from slam_core.params import ParamTable


def node_module_name(package: str, executable: str, plugin: str | None) -> str | None:
    """Return the module that defines a GRAPH entry's node, or None when it cannot be told."""
    if plugin:
        return plugin.partition(':')[0]
    try:
        distribution = importlib.metadata.distribution(package)
    except importlib.metadata.PackageNotFoundError:
        return None
    for entry_point in distribution.entry_points:
        if entry_point.group == 'console_scripts' and entry_point.name == executable:
            return entry_point.module
    return None


def parameter_table(package: str, executable: str, plugin: str | None) -> ParamTable | None:
    """Return the declaration table of a GRAPH entry's node, or None when it has none."""
    module_name = node_module_name(package, executable, plugin)
    if module_name is None:
        return None
    try:
        module = importlib.import_module(module_name)
    except ImportError:
        return None  # the runner reports a plugin that cannot be imported when it starts it
    table = getattr(module, 'PARAMETERS', None)
    return table if isinstance(table, ParamTable) else None


def check_graph_parameters(graph: Graph) -> None:
    """Raise GraphError for a parameter of a GRAPH entry that its node does not accept."""
    for node in graph.nodes:
        table = parameter_table(node.package, node.executable, node.plugin)
        if table is None:
            continue
        for index, source in enumerate(node.parameters):
            where = f'{node.key}.parameters[{index}]'
            if isinstance(source, dict):
                _check(graph, table, source, where, where)
            else:
                _check_file(graph, node, table, source, where)
        if node.respawn_parameters:
            where = f'{node.key}.respawn_parameters'
            _check(graph, table, node.respawn_parameters, where, where)


def _check_file(graph: Graph, node: NodeSpec, table: ParamTable, path: Path, where: str) -> None:
    document: Any = yaml.safe_load(path.read_text(encoding='utf-8'))  # checked by load_graph
    full_name = f'{node.namespace}/{node.name}'
    keys = {'/**', node.name, f'/{node.name}', full_name, full_name.lstrip('/')}
    if not isinstance(document, dict):
        return
    for key, section in document.items():
        if key in keys and isinstance(section, dict):
            values = section.get('ros__parameters')
            if isinstance(values, dict):
                label = f'{where}: parameter file {str(path)!r}, section {key!r}'
                _check(graph, table, values, label, where)


def _check(
    graph: Graph, table: ParamTable, values: dict[str, Any], label: str, where: str
) -> None:
    try:
        table.check_names(values, where=label)
        for name, value in values.items():
            if name in table:
                table.validate_one(name, value)
                table.check_ros_type(name, value)
    except ParameterError as err:
        text = str(err)
        raise graph.error(where, text.removeprefix(f'{where}: ')) from None
