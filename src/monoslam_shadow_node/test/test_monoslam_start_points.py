"""A depth start's points hold the map's scale: MonoSLAM keeps them when they are not found
where predicted (a person in front, a track the tracker dropped) so that they can be found
again under their id, while a feature of its own that is not found is deleted."""

from __future__ import annotations

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    TRACKING,
    MonoSlamConfig,
    MonoSlamFrame,
)
from slam_core.camera import CameraModel

CAMERA = CameraModel(
    640, 480, np.array([[500.0, 0, 320.0], [0, 500.0, 240.0], [0, 0, 1]]), np.zeros(5)
)  # fmt: skip
RNG = np.random.default_rng(5)
POINTS = np.column_stack([RNG.uniform(-1.5, 1.5, (60, 2)), RNG.uniform(2.5, 4.0, 60)])
START = np.arange(30)  # the points with a depth in the first image
STEP_NS = 33_000_000


def _frame(index: int, hidden: list[int]) -> MonoSlamFrame:
    centre = np.array([0.003 * index, 0.001 * index, 0.0])
    pixels = CAMERA.project(POINTS - centre) + RNG.normal(0.0, 0.5, (len(POINTS), 2))
    ids = np.arange(len(POINTS))
    keep = ~np.isin(ids, hidden)
    depths = None
    if index == 0:
        depths = np.where(np.isin(ids, START), POINTS[:, 2], np.nan)[keep]
    return MonoSlamFrame(index * STEP_NS, ids[keep].astype(np.int64), pixels[keep],
                         depths_m=depths)  # fmt: skip


def test_start_points_stay_when_not_found_and_are_measured_again() -> None:
    config = MonoSlamConfig(known_points_source='depth', initialize='all', target_measured=60)
    slam = MonoSlam(CAMERA, config)
    removed: dict[int, str] = {}
    for index in range(20):  # the start, then new features enter from the other tracks
        assert slam.process(_frame(index, [])).status == TRACKING
    in_map = {p.id: p.source for p in slam.map_points() if p.active}
    started = sorted(i for i, source in in_map.items() if source == 'start')
    assert set(started) <= set(START.tolist()) and len(started) >= 15, in_map
    new = sorted(i for i, source in in_map.items() if source == 'new')[:8]
    assert len(new) == 8, in_map
    hidden = started[:8] + new
    for index in range(20, 20 + 6 * config.failure_window):  # predicted in view, not found
        result = slam.process(_frame(index, hidden))
        assert result.status == TRACKING
        removed.update(result.removed)
    assert {i: removed.get(i) for i in new} == dict.fromkeys(new, 'failed')
    assert not set(removed) & set(started), removed
    result = slam.process(_frame(20 + 6 * config.failure_window, []))
    assert set(started[:8]) <= set(result.measured_ids)  # found again under their ids
