"""EM-SAM online (core.incremental) on the project's office bag, replayed offline.

bags/office_moveable.mcap (seed 7): 29 static wall markers and 10 desk markers (ids
100-109) that move from office 1 to office 2 while the robot is in the corridor. Keyframes
enter the smoother one at a time, as the mapper feeds them online.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from em_sam_node.core.assembly import MappingData
from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.incremental import IncrementalEmSam
from em_sam_node.core.incremental_types import IncrementalConfig
from em_sam_node.offline import replay_bag

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'office_moveable.mcap'
MOVED = frozenset(range(100, 110))


@pytest.fixture(scope='module')
def office() -> MappingData:
    return replay_bag(BAG).data


def _replay(data: MappingData, smoother: IncrementalEmSam) -> dict[int, int]:
    """Feed the run one keyframe at a time; return the static markers flagged on the way
    (id: first keyframe)."""
    incoming = {int(to): m for m, to in enumerate(data.odometry_to.tolist())}
    rows_of: dict[int, list[int]] = {}
    for k, keyframe in enumerate(data.obs_keyframe.tolist()):
        rows_of.setdefault(keyframe, []).append(k)
    wrongly: dict[int, int] = {}
    for index in range(data.num_keyframes):
        m = incoming.get(index)
        odometry = None if m is None else (data.odometry_u[m], data.odometry_cov[m])
        sightings = [
            (int(data.obs_landmark_id[k]), data.obs_z[k], data.obs_cov[k])
            for k in rows_of.get(index, [])
        ]
        for landmark in smoother.add_keyframe(odometry, sightings).moveable - MOVED:
            wrongly.setdefault(landmark, index)
    return wrongly


@pytest.mark.slow
def test_the_office_run_online_flags_no_static_marker_at_any_keyframe(office: MappingData) -> None:
    """Every keyframe's moveable set holds no static marker, and the run ends with the ten
    moved ones: a moved marker's new sightings never pull the path (before the smoother
    held such sightings out, statics were flagged for up to 140 keyframes on the way)."""
    smoother = IncrementalEmSam(EmConfig(), office.prior_pose, office.prior_cov)
    wrongly = _replay(office, smoother)
    assert not wrongly, f'static markers flagged (first keyframe): {wrongly}'
    assert smoother.moveable == MOVED
    assert smoother.kept_from == 0  # the run is shorter than the default horizon
    assert np.all(np.isfinite(smoother.poses()))


def test_a_short_horizon_keeps_the_smoother_small_and_the_answer_the_same(
    office: MappingData,
) -> None:
    """With a horizon of 200 keyframes the smoother marginalizes all but the latest 200-220
    poses, and the markers the robot comes back to return under their anchors: still no
    static marker flagged at any keyframe, and the ten moved ones at the end."""
    horizon = 200
    smoother = IncrementalEmSam(
        EmConfig(), office.prior_pose, office.prior_cov, IncrementalConfig(horizon=horizon)
    )
    wrongly = _replay(office, smoother)
    newest, block = office.num_keyframes - 1, horizon // 10  # it marginalizes a block at a time
    assert newest - horizon - block < smoother.kept_from <= newest - horizon
    assert smoother.returned > 0  # markers left the smoother and came back
    assert not wrongly, f'static markers flagged (first keyframe): {wrongly}'
    assert smoother.moveable == MOVED
    assert np.all(np.isfinite(smoother.poses()))
    assert len(smoother.landmark_positions()) == len(set(office.obs_landmark_id.tolist()))
