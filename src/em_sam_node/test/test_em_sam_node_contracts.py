"""The EM-SAM nodes' docstrings and config YAMLs agree with the parameters they declare."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import pytest

from em_sam_node import em_sam_mapper_node, odometry_ingest_node
from slam_ros.testing.node_contract import (
    config_mismatches,
    docstring_mismatches,
    undocumented_parameters,
)

CONFIG = Path(__file__).resolve().parents[1] / 'config'
NODES = [
    (odometry_ingest_node, 'odometry_ingest.yaml'),
    (em_sam_mapper_node, 'em_sam_mapper.yaml'),
]


@pytest.mark.parametrize(('module', 'config'), NODES, ids=[c for _, c in NODES])
def test_docstring_lists_every_parameter(module: ModuleType, config: str) -> None:
    assert undocumented_parameters(module) == []


@pytest.mark.parametrize(('module', 'config'), NODES, ids=[c for _, c in NODES])
def test_config_yaml_matches_declared_parameters(module: ModuleType, config: str) -> None:
    assert config_mismatches(module, CONFIG / config) == []


@pytest.mark.parametrize(('module', 'config'), NODES, ids=[c for _, c in NODES])
def test_docstring_types_and_defaults_match_the_declaration(
    module: ModuleType, config: str
) -> None:
    assert docstring_mismatches(module) == []
