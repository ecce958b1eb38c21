"""Known points of an imported RGB-D sequence (``tum_rgbd_sequence``): tracks whose world
position the first depth map gives, for MonoSLAM's start and scale (its known points are
zero-uncertainty landmarks, ``monoslam_init``), and how long they stay in view.

Choice (``choose_known_points``): the first image that has a pose, a depth map, and at least
``MIN_KNOWN_POINTS`` (4) candidates: tracks with a usable depth there
(``rgbd_depth.sample_depth``: no zero depth, not at a depth discontinuity) whose depth label
is static (seen with depth at least twice, consistently: ``depth_labels``). Each candidate's
world position is its back-projection at that image. To spread them, the image is cut into
a ``grid`` (4 x 4) and each cell keeps its candidate seen in the most images; of those, the
``cap`` (16) seen longest are the known points. Their ids stay the tracks' ids: the
sequence format makes a track whose id is in known_points.csv a known point in every frame
that sees it (``sequence_files``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from monoslam_shadow_node.core.monoslam_init import MIN_KNOWN_POINTS
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_sim.core.depth_labels import STATIC, DepthSightings, TrackLabels


@dataclass(frozen=True, eq=False)
class KnownPoints:
    """The chosen known points: the image they come from (index into the images given,
    -1: none), the candidates there, and id -> world point (3,) m."""

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
    """Return the known points (module docstring) of depth sightings whose ``frames`` are
    image indices; ``pixels[(image, id)]`` is a track's raw pixel in an image and
    ``lifetimes[id]`` the number of images that see it."""
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
    """Return how long known points stay in view, from sightings (frame (N,), id (N,)):
    images seeing each (min, median, max, and in seconds at ``rate_hz``), its first and last
    frame, and the frames seeing at least ``MIN_KNOWN_POINTS`` of them (count and last)."""
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
