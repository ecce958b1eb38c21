"""The contract check finds a docstring or config file that disagrees with the declaration."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

from slam_core.params import Param, ParamTable, ParamType
from slam_ros.testing.node_contract import (
    config_mismatches,
    docstring_mismatches,
    undocumented_parameters,
)


def node_module(doc: str) -> ModuleType:
    module = ModuleType('fake_node', doc)
    module.PARAMETERS = ParamTable(  # type: ignore[attr-defined]
        'fake_node',
        (
            Param('rate', 1.0, 'speed factor'),
            Param('mode', 'robust', 'mode'),
            Param('topics', [], 'topics', type=ParamType.STRING_ARRAY),
            Param('depth', 10, 'depth'),
        ),
    )
    return module


def test_docstring_types_and_defaults_are_compared() -> None:
    good = node_module("rate (double, 1.0), mode ('robust'), topics (string[], all), depth (10)")
    assert undocumented_parameters(good) == []
    assert docstring_mismatches(good) == []
    bad = node_module("rate (int, 2.0)  mode ('paper')  topics ([a])  depth (5)")
    problems = docstring_mismatches(bad)
    assert len(problems) == 4
    assert any('rate (int, 2.0): declared as double' in p for p in problems)
    assert any("mode ('paper'): the declared default is 'robust'" in p for p in problems)
    assert undocumented_parameters(node_module('rate and mode only')) == ['depth', 'topics']


def test_config_keys_types_and_values_are_compared(tmp_path: Path) -> None:
    module = node_module('')
    config = tmp_path / 'fake_node.yaml'
    config.write_text(
        "/**:\n  ros__parameters:\n    rate: 1.0\n    mode: robust\n    topics: ['']\n"
        '    depth: 10\n'
    )
    assert config_mismatches(module, config) == []
    config.write_text(
        '/**:\n  ros__parameters:\n    rate: 1\n    mode: paper\n    depth: x\n    speed: 2\n'
    )
    problems = '\n'.join(config_mismatches(module, config))
    assert 'fake_node.rate=1: must be a double for a ROS node' in problems
    assert "mode='paper' is not the declared default 'robust'" in problems
    assert "parameter fake_node.depth='x': must be an integer" in problems
    assert 'speed is not a parameter' in problems
    assert 'topics is missing' in problems
