"""The marker_detector node's docstring and config YAML agree with its declared parameters."""

from __future__ import annotations

from pathlib import Path

from marker_detector import marker_detector_node
from slam_ros.testing.node_contract import (
    config_mismatches,
    docstring_mismatches,
    undocumented_parameters,
)

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'marker_detector.yaml'


def test_docstring_lists_every_parameter() -> None:
    assert undocumented_parameters(marker_detector_node) == []


def test_config_yaml_matches_declared_parameters() -> None:
    assert config_mismatches(marker_detector_node, CONFIG) == []


def test_docstring_types_and_defaults_match_the_declaration() -> None:
    assert docstring_mismatches(marker_detector_node) == []
