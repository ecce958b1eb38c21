"""em_sam_mapper on a system its factors do not determine (real rclpy node, no graph): an
increment whose covariance is valid but so wide that it fixes nothing leaves the pose after
it undetermined. The solve is refused with the reason, counted on /diagnostics, and nothing
escapes the callback; with the increment's true covariance the same data solve."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_mapper import SECOND_NS, increment, observation

from em_sam_node.mapper.node import EmSamMapperNode


def _solve(ros_context: None, covariance_scale: float) -> tuple[str, EmSamMapperNode]:
    node = EmSamMapperNode()
    step = increment(0.0, 1.0, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    node.mapper.add_increment(
        dataclasses.replace(step, covariance=step.covariance * covariance_scale)
    )
    node.mapper.add_observation(observation(SECOND_NS))
    return node.optimize(), node


def test_an_undetermined_system_is_refused_and_counted(ros_context: None) -> None:
    summary, node = _solve(ros_context, 1e16)
    try:
        assert summary.startswith('not solved: the normal equations are rank-deficient')
        assert node.unsolved == 1 and node.solves == 0
        assert node._counts()['solves not determined'] == 1
    finally:
        node.destroy_node()


def test_the_same_data_with_a_sane_covariance_solve(ros_context: None) -> None:
    summary, node = _solve(ros_context, 1.0)
    try:
        assert summary.startswith('EM-SAM') and node.solves == 1 and node.unsolved == 0
    finally:
        node.destroy_node()
