"""Declaring node parameters with descriptors and turning bad values into ParameterError.

Nodes list their parameters as ``ParamSpec`` tuples, declare them all with
``declare_parameters`` and validate the resulting dict into a frozen config dataclass.
Nothing here falls back to a default when a value is invalid.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
    ParameterUninitializedException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from slam_core.errors import ParameterError

ParamValue = bool | int | float | str | list[str] | list[float] | list[int] | list[bool]

_LIST_TYPES = {
    'string_array': Parameter.Type.STRING_ARRAY,
    'double_array': Parameter.Type.DOUBLE_ARRAY,
    'integer_array': Parameter.Type.INTEGER_ARRAY,
    'bool_array': Parameter.Type.BOOL_ARRAY,
}


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter: name (with a unit suffix where it has a unit), default, meaning.

    ``array_type`` is needed only for list parameters whose default is empty
    (one of ``string_array``, ``double_array``, ``integer_array``, ``bool_array``).
    """

    name: str
    default: ParamValue
    description: str
    array_type: str | None = None
    read_only: bool = True

    def parameter_type(self) -> Parameter.Type:
        """Return the ROS parameter type of this spec."""
        if isinstance(self.default, list):
            if self.array_type is not None:
                return _LIST_TYPES[self.array_type]
            if not self.default:
                msg = f'ParamSpec {self.name!r}: an empty list default needs array_type'
                raise ValueError(msg)
        return Parameter.Type.from_parameter_value(self.default)


def declare_parameters(node: Node, specs: Iterable[ParamSpec]) -> dict[str, Any]:
    """Declare every spec on ``node``; return ``{name: value}`` with overrides applied.

    Raises:
        ParameterError: a value given for a parameter has the wrong type or is rejected.

    """
    values: dict[str, Any] = {}
    for spec in specs:
        ptype = spec.parameter_type()
        descriptor = ParameterDescriptor(
            description=spec.description, read_only=spec.read_only, type=ptype.value
        )
        try:
            if isinstance(spec.default, list) and not spec.default:
                node.declare_parameter(spec.name, ptype, descriptor)
            else:
                node.declare_parameter(spec.name, spec.default, descriptor)
        except (
            InvalidParameterTypeException,
            InvalidParameterValueException,
            ParameterException,
        ) as err:
            raise ParameterError(
                f'parameter {node.get_name()}.{spec.name}: {err} ({spec.description})'
            ) from err
        try:
            value = node.get_parameter(spec.name).value
        except ParameterUninitializedException:
            value = None
        if value is None:
            value = list(spec.default) if isinstance(spec.default, list) else spec.default
        elif isinstance(value, (list, tuple)) or hasattr(value, 'tolist'):
            value = list(value)
            if ptype == Parameter.Type.STRING_ARRAY:
                # YAML parameter files cannot hold an empty list; [''] stands for one.
                value = [item for item in value if item != '']
        values[spec.name] = value
    return values


def check(condition: bool, name: str, value: object, requirement: str) -> None:
    """Raise ParameterError ``parameter <name>=<value>: <requirement>`` unless condition."""
    if not condition:
        raise ParameterError(f'parameter {name}={value!r}: {requirement}')


def check_finite_positive(name: str, value: float) -> None:
    """Require a finite number > 0."""
    check(math.isfinite(value) and value > 0.0, name, value, 'must be a finite number > 0')


def check_finite_non_negative(name: str, value: float) -> None:
    """Require a finite number >= 0."""
    check(math.isfinite(value) and value >= 0.0, name, value, 'must be a finite number >= 0')


def parse_remaps(name: str, entries: Sequence[str]) -> dict[str, str]:
    """Parse ``['from:=to', ...]`` into a dict; reject malformed or duplicate entries."""
    remaps: dict[str, str] = {}
    for entry in entries:
        source, sep, target = entry.partition(':=')
        check(bool(sep and source and target), name, entry, "entries must look like 'from:=to'")
        check(source not in remaps, name, entry, f'{source!r} is remapped twice')
        remaps[source] = target
    return remaps
