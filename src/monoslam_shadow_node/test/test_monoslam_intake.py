"""Which tracks enter MonoSLAM's map (``monoslam_intake``): the counts a frame takes, the
farthest-first placement of new features and a handover's inverse depth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from monoslam_shadow_node.monoslam.core.monoslam_intake import (
    farthest_first,
    handover_inverse_depth,
    wanted,
)
from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig


def test_classic_mapping_fills_up_to_the_target_at_most_max_new_per_frame() -> None:
    config = MonoSlamConfig(initialize='all', target_measured=12, max_new_per_frame=5)
    assert wanted(config, offered=3, measured=10, cleared=0, trusted=10) == (0, 2)
    assert wanted(config, offered=3, measured=2, cleared=0, trusted=2) == (0, 5)
    assert wanted(config, offered=0, measured=20, cleared=0, trusted=20) == (0, 0)


def test_handovers_come_first_and_fills_count_what_fixes_the_camera() -> None:
    config = MonoSlamConfig(initialize='handover', target_measured=12, max_new_per_frame=5)
    # 8 measured, 6 of them trusted: 4 handovers taken (on probation: they fix nothing yet),
    # then fills up to the target counted on the trusted ones
    assert wanted(config, offered=10, measured=8, cleared=3, trusted=6) == (4, 5)
    assert wanted(dataclasses.replace(config, fill_undecided=False), 10, 8, 3, 6) == (4, 0)
    # with undecided_probation the handovers count against the cleared ones, the fills
    # against everything measured and taken
    waiting = dataclasses.replace(config, undecided_probation=True)
    assert wanted(waiting, offered=10, measured=8, cleared=3, trusted=6) == (9, 0)


def test_new_features_go_where_the_measured_ones_leave_the_largest_gap() -> None:
    pixels = np.array([[10.0, 0.0], [100.0, 0.0], [105.0, 0.0], [50.0, 0.0]])
    taken = np.array([[0.0, 0.0]])
    offered: list[int] = []

    def insert(k: int) -> bool:
        offered.append(k)
        return k != 2

    # 2 (farthest) is refused, then 1, then 3 (50 px from both); 0 lies 10 px from taken
    assert farthest_first(pixels, taken, 3, 20.0, insert) == [1, 3]
    assert offered == [2, 1, 3]
    # a refused candidate does not count against the budget, nor does it block the others
    assert farthest_first(pixels, np.zeros((0, 2)), 2, 1.0, insert) == [0, 1]


def test_a_handover_enters_at_its_distance_with_at_least_the_prior_variance() -> None:
    position, centre = np.array([0.0, 0.0, 4.0]), np.zeros(3)
    rho, variance = handover_inverse_depth(position, np.diag([1.0, 1.0, 0.16]), centre, 1e-6)
    assert rho == pytest.approx(0.25)
    assert variance == pytest.approx(0.16 * 0.25**4)  # the depth variance along the ray
    assert handover_inverse_depth(position, 1e-8 * np.eye(3), centre, 0.09) == (0.25, 0.09)
    assert handover_inverse_depth(centre, np.eye(3), centre, 0.09) is None
