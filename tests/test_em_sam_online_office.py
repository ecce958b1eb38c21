"""EM-SAM online (core.incremental) on the project's office bag, replayed offline.

bags/office_moveable.mcap (seed 7): 29 static wall markers and 10 desk markers (ids
100-109) that move from office 1 to office 2 while the robot is in the corridor. Keyframes
enter the smoother one at a time, as the mapper feeds them online.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.incremental import IncrementalEmSam
from em_sam_node.offline import replay_bag

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'office_moveable.mcap'
MOVED = frozenset(range(100, 110))


def test_the_office_run_online_flags_no_static_marker_at_any_keyframe() -> None:
    """Every keyframe's moveable set holds no static marker, and the run ends with the ten
    moved ones: a moved marker's new sightings never pull the path (before the smoother
    held such sightings out, statics were flagged for up to 140 keyframes on the way)."""
    data = replay_bag(BAG).data
    smoother = IncrementalEmSam(EmConfig(), data.prior_pose, data.prior_cov)
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
    assert not wrongly, f'static markers flagged (first keyframe): {wrongly}'
    assert smoother.moveable == MOVED
    assert np.all(np.isfinite(smoother.poses()))
