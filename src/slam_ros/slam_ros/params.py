"""Declaring a ``ParamTable`` on an rclpy node, and remap lists (docs/design/ros_and_core.md)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
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


def declare_parameters(node: Node, table: ParamTable) -> dict[str, Any]:
    """Declare ``table`` on ``node`` with descriptors; return the validated values."""
    overrides = getattr(node, '_parameter_overrides', {})
    table.check_names(
        overrides,
        where=f'node {node.get_fully_qualified_name()}: parameter override (-p, --params-file '
        'or parameter_overrides)',
    )
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
    return current_values(node, table)


def current_values(node: Node, table: ParamTable) -> dict[str, Any]:
    """The validated values of ``table``'s parameters as declared on ``node`` now."""
    values: dict[str, Any] = {}
    for param in table:
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


def parse_remaps(name: str, entries: Sequence[str]) -> dict[str, str]:
    """Parse ``['from:=to', ...]`` into a dict; reject malformed or duplicate entries."""
    remaps: dict[str, str] = {}
    for entry in entries:
        source, sep, target = entry.partition(':=')
        if not (sep and source and target):
            raise ParameterError(f"parameter {name}={entry!r}: entries must look like 'from:=to'")
        if source in remaps:
            raise ParameterError(f'parameter {name}={entry!r}: {source!r} is remapped twice')
        remaps[source] = target
    return remaps


def remap_rule(entries: Sequence[str]) -> str | None:
    """Validator for a remap list: the rule ``parse_remaps`` finds broken, or None."""
    try:
        parse_remaps('remap', entries)
    except ParameterError as err:
        return str(err).partition(': ')[2]
    return None


def check_parameter_files(args: Sequence[str], table: ParamTable) -> None:
    """ParameterError for an unknown key in the ``--params-file`` files of a node's ROS args."""
    node_name = table.node
    files: list[str] = []
    in_ros_args = False
    for index, arg in enumerate(args):
        if arg == '--ros-args':
            in_ros_args = True
        elif arg == '--':
            in_ros_args = False
        elif in_ros_args and arg == '--params-file' and index + 1 < len(args):
            files.append(args[index + 1])
        elif in_ros_args and arg.startswith(('__node:=', '__name:=')):
            node_name = arg.partition(':=')[2]
    for path in files:
        table.check_file(path, node_name=node_name)
