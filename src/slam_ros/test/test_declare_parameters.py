"""slam_ros.params: a ParamTable declared on a real rclpy node gets descriptors with its
rules and ranges, and bad overrides are refused in the one error style."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter

from slam_core.errors import ParameterError
from slam_core.params import POSITIVE, PROBABILITY, Param, ParamTable, ParamType, Range
from slam_ros.params import check_parameter_files, declare_parameters, updated_values

pytestmark = pytest.mark.topic

TABLE = ParamTable(
    'declare_test',
    (
        Param('rate_hz', 10.0, 'rate, Hz', range=POSITIVE),
        Param('alpha', 0.05, 'level', range=PROBABILITY, read_only=False),
        Param('depth', 10, 'depth', range=Range(1, 100)),
        Param('topics', [], 'topics', type=ParamType.STRING_ARRAY),
    ),
)


def make_node(*overrides: Parameter) -> Node:
    return Node('declare_test', parameter_overrides=list(overrides))


def test_values_and_descriptors(ros_context: None) -> None:
    node = make_node(Parameter('depth', value=20), Parameter('topics', value=['']))
    try:
        values = declare_parameters(node, TABLE)
        assert values == {'rate_hz': 10.0, 'alpha': 0.05, 'depth': 20, 'topics': []}
        rate = node.describe_parameter('rate_hz')
        assert rate.read_only and rate.additional_constraints == 'must be > 0'
        assert rate.floating_point_range[0].to_value == math.inf
        depth = node.describe_parameter('depth')
        assert (depth.integer_range[0].from_value, depth.integer_range[0].to_value) == (1, 100)
        assert not node.describe_parameter('alpha').read_only
        changed = updated_values(TABLE, values, [Parameter('alpha', value=0.1)])
        assert changed['alpha'] == 0.1
        with pytest.raises(ParameterError, match=r'declare_test\.alpha=1\.0: must be in'):
            updated_values(TABLE, values, [Parameter('alpha', value=1.0)])
    finally:
        node.destroy_node()


@pytest.mark.parametrize(
    ('override', 'message'),
    [
        (Parameter('rate_hz', value=0.0), r'^parameter declare_test\.rate_hz=0\.0: must be > 0$'),
        (Parameter('depth', value=500), r'^parameter declare_test\.depth=500: must be in \[1'),
        (Parameter('rate_hz', value=5), r'^parameter declare_test\.rate_hz=5: must be a double'),
        (Parameter('depth', value='x'), r"^parameter declare_test\.depth='x': must be an int"),
    ],
)
def test_bad_overrides_are_refused_naming_node_and_parameter(
    ros_context: None, override: Parameter, message: str
) -> None:
    node = make_node(override)
    try:
        with pytest.raises(ParameterError, match=message):
            declare_parameters(node, TABLE)
    finally:
        node.destroy_node()


def test_unknown_overrides_are_refused_with_the_closest_name(ros_context: None) -> None:
    node = make_node(Parameter('rate_hx', value=1.0), Parameter('use_sim_time', value=True))
    try:
        with pytest.raises(ParameterError, match=r"'rate_hx' is not a parameter of node "):
            declare_parameters(node, TABLE)
    finally:
        node.destroy_node()


def test_parameter_files_on_the_command_line_are_checked(tmp_path: Path) -> None:
    path = tmp_path / 'p.yaml'
    path.write_text('declare_test:\n  ros__parameters:\n    depht: 3\n', encoding='utf-8')
    args = ['--ros-args', '--params-file', str(path)]
    with pytest.raises(ParameterError) as caught:
        check_parameter_files(args, TABLE)
    assert str(path) in str(caught.value)
    assert "'depht' is not a parameter of node declare_test; did you mean 'depth'?" in str(
        caught.value
    )
    check_parameter_files([*args, '-r', '__node:=renamed'], TABLE)  # a section for another node
