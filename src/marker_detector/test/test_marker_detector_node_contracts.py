"""The marker_detector node's help, docstring and config YAML agree with its declared
parameters; its docstring stays a screen long."""

from __future__ import annotations

from pathlib import Path

from marker_detector.detector import node as marker_detector_node
from slam_ros.testing.node_contract import (
    NODE_DOCSTRING_MAX_LINES,
    config_mismatches,
    docstring_lines,
    docstring_mismatches,
    help_without_parameters,
)

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'marker_detector.yaml'


def test_help_lists_every_parameter_and_the_docstring_stays_short() -> None:
    assert help_without_parameters(marker_detector_node, 'marker_detector') == []
    assert docstring_lines(marker_detector_node) <= NODE_DOCSTRING_MAX_LINES


def test_config_yaml_matches_declared_parameters() -> None:
    assert config_mismatches(marker_detector_node, CONFIG) == []


def test_docstring_types_and_defaults_match_the_declaration() -> None:
    assert docstring_mismatches(marker_detector_node) == []


def test_the_help_states_the_hold_limits_the_node_uses() -> None:
    from marker_detector.detector import node as marker_detector_node

    doc = ' '.join((marker_detector_node.__doc__ or '').split())
    assert f'{marker_detector_node.HOLD_S:g} s of stamps' in doc
    assert f'{marker_detector_node.HOLD_MAX_BYTES / 2**20:g} MiB of images' in doc
