"""Each node's help, docstring and config YAML agree with the parameters it declares; its
docstring stays a screen long."""

from __future__ import annotations

from pathlib import Path

import pytest

from slam_bringup import bag_player, bag_recorder
from slam_ros.testing.node_contract import (
    NODE_DOCSTRING_MAX_LINES,
    config_mismatches,
    docstring_lines,
    docstring_mismatches,
    help_without_parameters,
)

CONFIG = Path(__file__).resolve().parents[1] / 'config'
NODES = [(bag_player, 'bag_player.yaml'), (bag_recorder, 'bag_recorder.yaml')]


@pytest.mark.parametrize(('module', 'config'), NODES, ids=[c for _, c in NODES])
def test_help_lists_every_parameter_and_the_docstring_stays_short(
    module: object, config: str
) -> None:
    assert help_without_parameters(module, config.removesuffix('.yaml')) == []  # type: ignore[arg-type]
    assert docstring_lines(module) <= NODE_DOCSTRING_MAX_LINES  # type: ignore[arg-type]


@pytest.mark.parametrize(('module', 'config'), NODES, ids=[c for _, c in NODES])
def test_config_yaml_matches_declared_parameters(module: object, config: str) -> None:
    assert config_mismatches(module, CONFIG / config) == []  # type: ignore[arg-type]


@pytest.mark.parametrize(('module', 'config'), NODES, ids=[c for _, c in NODES])
def test_docstring_types_and_defaults_match_the_declaration(module: object, config: str) -> None:
    assert docstring_mismatches(module) == []  # type: ignore[arg-type]


def test_contract_check_catches_a_stray_key(tmp_path: Path) -> None:
    stray = tmp_path / 'bad.yaml'
    stray.write_text('/**:\n  ros__parameters:\n    rate: fast\n    speed: 2.0\n')
    problems = config_mismatches(bag_player, stray)  # type: ignore[arg-type]
    assert any('speed is not a parameter' in p for p in problems)
    assert any('rate=' in p for p in problems)
    assert any('bag_path is missing' in p for p in problems)
