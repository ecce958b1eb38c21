"""A node's docstring and config checked against PARAMETERS (docs/design/ros_and_core.md)."""

from __future__ import annotations

import math
import re
from pathlib import Path
from types import ModuleType
from typing import Any

import yaml

from slam_core.cli import node_help
from slam_core.errors import ParameterError
from slam_core.params import Param, ParamTable, ParamType

_TYPE_NAMES = {
    'bool': ParamType.BOOL,
    'int': ParamType.INTEGER,
    'integer': ParamType.INTEGER,
    'double': ParamType.DOUBLE,
    'float': ParamType.DOUBLE,
    'string': ParamType.STRING,
    'bool[]': ParamType.BOOL_ARRAY,
    'int[]': ParamType.INTEGER_ARRAY,
    'double[]': ParamType.DOUBLE_ARRAY,
    'string[]': ParamType.STRING_ARRAY,
}


def declared(module: ModuleType) -> ParamTable:
    """Return the module's parameter table (TypeError when it has none)."""
    table = getattr(module, 'PARAMETERS', None)
    if not isinstance(table, ParamTable):
        raise TypeError(f'{module.__name__}.PARAMETERS is not a ParamTable')
    return table


NODE_DOCSTRING_MAX_LINES = 30
"""A node module's docstring says what the node does in a screen; the rest is in docs/."""


def help_without_parameters(module: ModuleType, prog: str) -> list[str]:
    """Declared parameter names that the node's ``--help`` does not list with type and default."""
    text = node_help(prog, module.__doc__, declared(module))
    return sorted(
        p.name for p in declared(module) if not re.search(rf'^  {p.name} \(', text, re.M)
    )


def docstring_lines(module: ModuleType) -> int:
    """Return the number of lines of the module's docstring."""
    return len((module.__doc__ or '').strip('\n').splitlines())


def undocumented_parameters(module: ModuleType) -> list[str]:
    """Return declared parameter names that the module docstring does not mention."""
    text = module.__doc__ or ''
    return sorted(p.name for p in declared(module) if not re.search(rf'\b{p.name}\b', text))


def docstring_mismatches(module: ModuleType) -> list[str]:
    """Where the docstring's ``name (type, default)`` disagrees with the declaration."""
    text = module.__doc__ or ''
    problems = []
    for param in declared(module):
        for match in re.finditer(rf'(?<![\w.]){param.name} \(([^()\n]*)\)', text):
            problem = _annotation_problem(param, match.group(1).strip())
            if problem:
                problems.append(
                    f'{module.__name__} docstring: {param.name} ({match[1]}): {problem}'
                )
    return sorted(problems)


def _annotation_problem(param: Param, annotation: str) -> str | None:
    head, sep, rest = annotation.partition(', ')
    if head in _TYPE_NAMES:
        if _TYPE_NAMES[head] is not param.param_type:
            return f'declared as {param.param_type.value}'
        annotation = rest if sep else ''
    if not annotation:
        return None
    try:
        written = yaml.safe_load(annotation)
    except yaml.YAMLError:
        return None
    comparable = isinstance(written, bool | int | float | list) or (
        isinstance(written, str) and annotation[:1] in ('"', "'")
    )
    if comparable and not _same(written, param.default):
        return f'the declared default is {param.default!r}'
    return None


def _same(written: object, default: object) -> bool:
    if isinstance(default, bool) or isinstance(written, bool):
        return written is default
    if isinstance(default, int | float) and isinstance(written, int | float):
        return math.isclose(written, default, rel_tol=1e-12) or written == default
    if isinstance(default, list) and isinstance(written, list):
        return len(default) == len(written) and all(map(_same, written, default))
    return written == default


def config_mismatches(module: ModuleType, config_path: Path) -> list[str]:
    """Differences between a node's config YAML and its declaration."""
    document: Any = yaml.safe_load(config_path.read_text(encoding='utf-8'))
    try:
        values: dict[str, Any] = document['/**']['ros__parameters']
    except (KeyError, TypeError):
        return [f'{config_path}: no "/**: ros__parameters:" mapping']
    table = declared(module)
    problems = [
        f'{config_path}: {name} is not a parameter' for name in set(values) - {*table.names}
    ]
    problems += [f'{config_path}: {name} is missing' for name in {*table.names} - set(values)]
    for name in set(values) & {*table.names}:
        param = table[name]
        try:
            value = table.validate_one(name, values[name])
            table.check_ros_type(name, values[name])
        except ParameterError as err:
            problems.append(f'{config_path}: {err}')
            continue
        if not _same(value, param.default):
            problems.append(
                f'{config_path}: {name}={values[name]!r} is not the declared default '
                f'{param.default!r}'
            )
    return sorted(problems)
