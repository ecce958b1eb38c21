"""Checks that keep a node's documentation and config file honest against its parameters.

A node module lists its parameters as ``PARAMETERS`` (a sequence of ParamSpec); its module
docstring must mention each one, and its ``config/<node>.yaml`` must set exactly those keys
under ``/**: ros__parameters:`` with values of the declared types.
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any

import yaml

from slam_ros.params import ParamSpec


def declared(module: ModuleType) -> dict[str, ParamSpec]:
    """Return the module's ParamSpecs by name."""
    return {spec.name: spec for spec in module.PARAMETERS}


def undocumented_parameters(module: ModuleType) -> list[str]:
    """Return declared parameter names that the module docstring does not mention."""
    text = module.__doc__ or ''
    return sorted(name for name in declared(module) if name not in text)


def config_mismatches(module: ModuleType, config_path: Path) -> list[str]:
    """Return the differences between a node's config YAML and its declared parameters."""
    document: Any = yaml.safe_load(config_path.read_text(encoding='utf-8'))
    try:
        values: dict[str, Any] = document['/**']['ros__parameters']
    except (KeyError, TypeError):
        return [f'{config_path}: no "/**: ros__parameters:" mapping']
    specs = declared(module)
    problems = [f'{config_path}: {name} is not a parameter' for name in set(values) - set(specs)]
    problems += [f'{config_path}: {name} is missing' for name in set(specs) - set(values)]
    for name in set(values) & set(specs):
        expected = type(specs[name].default)
        value = values[name]
        compatible = isinstance(value, expected) or (expected is float and isinstance(value, int))
        if not compatible:
            problems.append(
                f'{config_path}: {name}={value!r} is not a {expected.__name__} like its default'
            )
    return sorted(problems)
