"""The config check itself catches a stray key, a wrong type and a missing one (the contract
every node meets is in tests/test_node_parameter_contracts.py)."""

from __future__ import annotations

from pathlib import Path

from slam_bringup import bag_player, bag_recorder
from slam_ros.testing.node_contract import (
    config_mismatches,
)

CONFIG = Path(__file__).resolve().parents[1] / 'config'
NODES = [(bag_player, 'bag_player.yaml'), (bag_recorder, 'bag_recorder.yaml')]


def test_contract_check_catches_a_stray_key(tmp_path: Path) -> None:
    stray = tmp_path / 'bad.yaml'
    stray.write_text('/**:\n  ros__parameters:\n    rate: fast\n    speed: 2.0\n')
    problems = config_mismatches(bag_player, stray)  # type: ignore[arg-type]
    assert any('speed is not a parameter' in p for p in problems)
    assert any('rate=' in p for p in problems)
    assert any('bag_path is missing' in p for p in problems)
