"""Known points of an imported RGB-D sequence from its first depth map, and their visibility.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_init import MIN_KNOWN_POINTS
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_sim.core.depth_labels import STATIC, DepthSightings, TrackLabels


@dataclass(frozen=True, eq=False)
class KnownPoints:
    """The chosen known points: image index (-1: none), candidates, id -> world point (3,) m."""

    image: int
    candidates: int
    points: dict[int, FloatArray]


def choose_known_points(
    camera: CameraModel,
    sightings: DepthSightings,
    pixels: Mapping[tuple[int, int], tuple[float, float]],
    labels: TrackLabels,
    lifetimes: Mapping[int, int],
    *,
    cap: int = 16,
    grid: tuple[int, int] = (4, 4),
) -> KnownPoints:
    """Return the known points of depth sightings (``frames``: image indices), with
    ``pixels[(image, id)]`` raw pixels and ``lifetimes[id]`` images."""
    if cap < 1:
        return KnownPoints(-1, 0, {})
    static = labels.label_of(sightings.ids) == STATIC
    for image in np.unique(sightings.frames[static]).tolist():
        here = np.flatnonzero(static & (sightings.frames == image))
        if len(here) < MIN_KNOWN_POINTS:
            continue
        best: dict[tuple[int, int], int] = {}
        for row in here.tolist():
            track = int(sightings.ids[row])
            u, v = pixels[(image, track)]
            cell = (
                min(int(v * grid[0] / camera.height), grid[0] - 1),
                min(int(u * grid[1] / camera.width), grid[1] - 1),
            )
            holder = best.get(cell)
            if holder is None or _longer(track, int(sightings.ids[holder]), lifetimes):
                best[cell] = row
        chosen = sorted(
            best.values(), key=lambda r: (-lifetimes.get(int(sightings.ids[r]), 0), r)
        )[:cap]
        points = {int(sightings.ids[r]): sightings.points[r].copy() for r in chosen}
        return KnownPoints(int(image), len(here), dict(sorted(points.items())))
    return KnownPoints(-1, 0, {})


def _longer(track: int, other: int, lifetimes: Mapping[int, int]) -> bool:
    """Whether ``track`` is seen in more images than ``other`` (ties: the lower id)."""
    mine, theirs = lifetimes.get(track, 0), lifetimes.get(other, 0)
    return mine > theirs or (mine == theirs and track < other)


def visibility(
    frames: IntArray, ids: IntArray, known_ids: list[int], rate_hz: float
) -> dict[str, object]:
    """Return how long known points stay in view, from sightings (frame (N,), id (N,)): images
    per point (min, median, max; s at ``rate_hz``), first and last frame, and the frames
    seeing at least ``MIN_KNOWN_POINTS`` of them (count, last)."""
    if not known_ids:
        return {'count': 0}
    known = np.isin(ids, known_ids)
    per_point = np.array([np.count_nonzero(ids == k) for k in known_ids])
    seen_per_frame = np.bincount(frames[known], minlength=int(frames.max(initial=0)) + 1)
    enough = np.flatnonzero(seen_per_frame >= MIN_KNOWN_POINTS)
    return {
        'count': len(known_ids),
        'frames_in_view_min': int(per_point.min()),
        'frames_in_view_median': float(np.median(per_point)),
        'frames_in_view_max': int(per_point.max()),
        'seconds_in_view_median': float(np.median(per_point) / rate_hz),
        'last_frame_per_point': {int(k): int(frames[ids == k].max()) for k in known_ids},
        'frames_with_at_least_4': len(enough),
        'last_frame_with_at_least_4': int(enough.max()) if len(enough) else -1,
    }
