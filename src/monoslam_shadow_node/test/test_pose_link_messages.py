"""Pairing poses with their links (``pose_link_messages.PoseLinks``) whichever comes first,
and reading slam_interfaces/PoseLink."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from monoslam_shadow_node.common.core.inputs import CameraPose
from monoslam_shadow_node.common.pose_link_messages import (
    PoseLinkInput,
    PoseLinks,
    fill_pose_link,
    link_from_message,
)


def _pose(stamp_ns: int) -> CameraPose:
    return CameraPose(stamp_ns, 'map', np.eye(3), np.zeros(3), np.eye(6))


def _link(stamp_ns: int) -> PoseLinkInput:
    return PoseLinkInput(stamp_ns, (stamp_ns - 1,), np.full((1, 6, 6), 0.5))


def test_a_pose_waits_for_its_link_and_a_link_for_its_pose() -> None:
    links = PoseLinks()
    (first,) = links.on_pose(_pose(10))  # no link seen yet: the source may have none
    assert first.cross_covariances is None
    assert links.on_link(_link(20)) == []  # the link first
    (second,) = links.on_pose(_pose(20))
    assert second.cross_stamps == (19,) and second.cross_covariances is not None
    assert links.on_pose(_pose(30)) == []  # links have come: this pose waits for its own
    (third,) = links.on_link(_link(30))
    assert third.cross_stamps == (29,)
    assert links.on_pose(_pose(40)) == []
    fourth, fifth = links.on_pose(_pose(50))[0], links.flush()  # 40's link never came
    assert fourth.stamp_ns == 40 and fourth.cross_covariances is None
    assert fifth[0].stamp_ns == 50
    assert (links.received, links.linked, links.unlinked) == (2, 2, 3)


def test_a_link_reads_back_as_written_and_a_bad_one_is_named() -> None:
    def time() -> SimpleNamespace:
        return SimpleNamespace(sec=0, nanosec=0)

    message = SimpleNamespace(header=SimpleNamespace(stamp=time(), frame_id=''))
    cross = np.arange(72, dtype=float).reshape(2, 6, 6)
    fill_pose_link(3_000_000_001, (1_000_000_000, 2_000_000_000), cross, 'map', message, time)
    link = link_from_message(message)
    assert link.stamp_ns == 3_000_000_001
    assert link.earlier_stamps == (1_000_000_000, 2_000_000_000)
    np.testing.assert_array_equal(link.cross_covariances, cross)
    message.cross_covariances = message.cross_covariances[:-1]
    with pytest.raises(ValueError, match='71 values for 2 earlier stamps'):
        link_from_message(message)
