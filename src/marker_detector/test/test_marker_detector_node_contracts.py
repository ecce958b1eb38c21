"""The marker_detector node's help states the limits it uses (the contract shared by every
node is in tests/test_node_parameter_contracts.py)."""

from __future__ import annotations

from marker_detector.detector import node as marker_detector_node


def test_the_help_states_the_hold_limits_the_node_uses() -> None:
    doc = ' '.join((marker_detector_node.__doc__ or '').split())
    assert f'{marker_detector_node.HOLD_S:g} s of stamps' in doc
    assert f'{marker_detector_node.HOLD_MAX_BYTES / 2**20:g} MiB of images' in doc
