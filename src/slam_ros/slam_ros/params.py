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

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
    ParameterUninitializedException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from slam_core.errors import ParameterError
from slam_core.params import Param, ParamTable, ParamType

ParamValue = bool | int | float | str | list[str] | list[float] | list[int] | list[bool]

_ROS_TYPES = {
    ParamType.BOOL: Parameter.Type.BOOL,
    ParamType.INTEGER: Parameter.Type.INTEGER,
    ParamType.DOUBLE: Parameter.Type.DOUBLE,
    ParamType.STRING: Parameter.Type.STRING,
    ParamType.BOOL_ARRAY: Parameter.Type.BOOL_ARRAY,
    ParamType.INTEGER_ARRAY: Parameter.Type.INTEGER_ARRAY,
    ParamType.DOUBLE_ARRAY: Parameter.Type.DOUBLE_ARRAY,
    ParamType.STRING_ARRAY: Parameter.Type.STRING_ARRAY,
}
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1
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


def declare_parameters(node: Node, specs: ParamTable | Iterable[ParamSpec]) -> dict[str, Any]:
    """Declare a node's parameters; return ``{name: value}`` with overrides applied.

    Given a ``ParamTable``, every parameter is declared with a descriptor (description, rules,
    read-only, the range where rclpy has one) and the values come back validated by the
    table. Raises ParameterError ``parameter <node>.<name>=<value>: <rule>``.
    """
    if isinstance(specs, ParamTable):
        return declare_table(node, specs)
    return _declare_specs(node, specs)


def descriptor(param: Param) -> ParameterDescriptor:
    """Return the rclpy descriptor of a declared parameter."""
    ptype = _ROS_TYPES[param.param_type]
    rules = param.rules()
    result = ParameterDescriptor(
        description=param.description,
        read_only=param.read_only,
        type=ptype.value,
        additional_constraints='; '.join(rules),
    )
    bounds = param.range
    if bounds is not None and param.param_type.element is ParamType.DOUBLE:
        low = -math.inf if bounds.low is None else float(bounds.low)
        high = math.inf if bounds.high is None else float(bounds.high)
        result.floating_point_range = [FloatingPointRange(from_value=low, to_value=high, step=0.0)]
    elif bounds is not None and param.param_type is ParamType.INTEGER:
        low_int = _INT64_MIN if bounds.low is None else math.ceil(bounds.low)
        high_int = _INT64_MAX if bounds.high is None else math.floor(bounds.high)
        result.integer_range = [IntegerRange(from_value=low_int, to_value=high_int, step=1)]
    return result


def declare_table(node: Node, table: ParamTable) -> dict[str, Any]:
    """Declare every parameter of ``table`` on ``node``; return the validated values."""
    values: dict[str, Any] = {}
    for param in table:
        ptype = _ROS_TYPES[param.param_type]
        try:
            if isinstance(param.default, list) and not param.default:
                node.declare_parameter(param.name, ptype, descriptor(param))
            else:
                node.declare_parameter(param.name, param.default, descriptor(param))
        except (
            InvalidParameterTypeException,
            InvalidParameterValueException,
            ParameterException,
        ) as err:
            raise _declare_error(node, table, param, err) from None
        try:
            value = node.get_parameter(param.name).value
        except ParameterUninitializedException:
            value = None
        if value is None:
            value = param.default_value()
        elif isinstance(value, (list, tuple)) or hasattr(value, 'tolist'):
            value = list(value)
        values[param.name] = value
    return table.validate(values)


def _declare_error(node: Node, table: ParamTable, param: Param, err: Exception) -> ParameterError:
    """Word a refused override like every other parameter error."""
    overrides = getattr(node, '_parameter_overrides', {})
    override = overrides.get(param.name)
    if override is None:
        return ParameterError(f'parameter {table.node}.{param.name}: {err}')
    value = override.value
    try:
        table.validate_one(param.name, value)
    except ParameterError as rejection:
        return rejection
    return table.fail(
        param.name,
        value,
        f'must be a {param.param_type.value} (write 1.0, not 1, for a double)',
    )


def updated_values(
    table: ParamTable, current: dict[str, Any], parameters: Iterable[Parameter]
) -> dict[str, Any]:
    """Return ``current`` with run-time changes validated and applied (ParameterError)."""
    values = dict(current)
    for parameter in parameters:
        if parameter.name in table:
            values[parameter.name] = table.validate_one(parameter.name, parameter.value)
    return values


def _declare_specs(node: Node, specs: Iterable[ParamSpec]) -> dict[str, Any]:
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


def remap_rule(entries: Sequence[str]) -> str | None:
    """Validator for a remap list: the rule ``parse_remaps`` finds broken, or None."""
    try:
        parse_remaps('remap', entries)
    except ParameterError as err:
        return str(err).partition(': ')[2]
    return None
