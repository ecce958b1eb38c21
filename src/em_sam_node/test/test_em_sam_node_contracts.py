"""The EM-SAM nodes' help, docstrings and config YAMLs agree with the parameters they declare;
their docstrings stay a screen long."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import pytest

from em_sam_node.mapper import node as em_sam_mapper_node
from em_sam_node.odometry_ingest import node as odometry_ingest_node
from slam_ros.testing.node_contract import (
    NODE_DOCSTRING_MAX_LINES,
    config_mismatches,
    docstring_lines,
    docstring_mismatches,
    help_without_parameters,
)

CONFIG = Path(__file__).resolve().parents[1] / 'config'
NODES = [
    (odometry_ingest_node, 'odometry_ingest.yaml'),
    (em_sam_mapper_node, 'em_sam_mapper.yaml'),
]


@pytest.mark.parametrize(('module', 'config'), NODES, ids=[c for _, c in NODES])
def test_help_lists_every_parameter_and_the_docstring_stays_short(
    module: ModuleType, config: str
) -> None:
    assert help_without_parameters(module, config.removesuffix('.yaml')) == []
    assert docstring_lines(module) <= NODE_DOCSTRING_MAX_LINES


@pytest.mark.parametrize(('module', 'config'), NODES, ids=[c for _, c in NODES])
def test_config_yaml_matches_declared_parameters(module: ModuleType, config: str) -> None:
    assert config_mismatches(module, CONFIG / config) == []


@pytest.mark.parametrize(('module', 'config'), NODES, ids=[c for _, c in NODES])
def test_docstring_types_and_defaults_match_the_declaration(
    module: ModuleType, config: str
) -> None:
    assert docstring_mismatches(module) == []
