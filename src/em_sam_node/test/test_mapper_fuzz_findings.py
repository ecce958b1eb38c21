"""What fuzzing the em_sam_mapper's inputs found (tests/fuzz_nodes.py): an increment or an
observation with a finite covariance that is not positive definite was taken, and the next
solve raised out of the node's timer ('a covariance is not positive definite')."""

from __future__ import annotations

import math

import numpy as np
import pytest

from em_sam_node.core.assembly import is_covariance
from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.inputs import Increment, Observation
from em_sam_node.mapper.processor import MapperConfig, MapperProcessor

S = 1_000_000_000


@pytest.mark.parametrize(
    'matrix',
    [
        np.zeros((3, 3)),
        -np.eye(3),
        np.diag([1.0, 1.0, 0.0]),
        np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),  # indefinite
        np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),  # not symmetric
        np.diag([1.0, math.nan, 1.0]),
        np.diag([1e-320, 1.0, 1.0]),  # its information is not finite
        np.eye(2)[:, :1],
    ],
)
def test_what_is_no_covariance(matrix: np.ndarray) -> None:
    assert not is_covariance(matrix)


def test_what_is_a_covariance() -> None:
    assert is_covariance(np.diag([1e-4, 1e-4, 1e-6]))
    assert is_covariance(np.array([[2.0, 0.3], [0.3, 1.0]]))


def increment(start_s: int, covariance: np.ndarray) -> Increment:
    return Increment(
        stamp_from_ns=start_s * S,
        stamp_to_ns=(start_s + 1) * S,
        u=np.array([0.5, 0.0, 0.1]),
        covariance=covariance,
        odom_pose_from=np.zeros(3),
        odom_pose_to=np.zeros(3),
    )


def test_a_covariance_that_is_not_positive_definite_is_dropped_and_counted() -> None:
    mapper = MapperProcessor(MapperConfig(em=EmConfig()))
    good = np.diag([1e-3, 1e-3, 1e-4])
    mapper.add_increment(increment(0, good))
    mapper.add_increment(increment(1, -good))
    assert mapper.dropped_increments == 1
    mapper.add_increment(increment(1, good))
    mapper.add_observation(Observation(S, 3, np.array([2.0, 0.1]), np.zeros((2, 2))))
    mapper.add_observation(Observation(S, 3, np.array([2.0, 0.1]), np.diag([0.01, 0.001])))
    mapper.add_observation(Observation(2 * S, 3, np.array([2.1, 0.1]), np.diag([0.01, 0.001])))
    assert mapper.dropped_observations == 1 and len(mapper.increments) == 2
    mapper.optimize()  # used to raise 'a covariance is not positive definite'
