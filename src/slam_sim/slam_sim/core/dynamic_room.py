"""The dynamic scene's 10 x 8 x 3 m room with cabinets, and the static points on it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam_core.arrays import FloatArray
from slam_sim.core.dynamic_config import OBJECT_SPACE_M, ROOM_SIZE_M

# Static point fractions: far wall, two side walls, floor, ceiling; the rest on cabinets.
_SURFACE_FRACTIONS = (0.30, 0.12, 0.12, 0.14, 0.06)
FAR_WALL_FRACTION = _SURFACE_FRACTIONS[0]
_LOOP_PATCH_HALF_WIDTH_M = 3.0
_CABINETS = 5


@dataclass(frozen=True)
class RoomLayout:
    """The room [0, size_m] in map (m), cabinets (B, 3) min/max, object free space."""

    size_m: FloatArray
    cabinets_min_m: FloatArray
    cabinets_max_m: FloatArray
    object_space_min_m: FloatArray
    object_space_max_m: FloatArray


def sample_room(rng: np.random.Generator) -> RoomLayout:
    """Return the 10 x 8 x 3 m room with cabinets (0.4-0.8 deep) along the side and far walls."""
    size = np.array(ROOM_SIZE_M)
    lows, highs = [], []
    for _ in range(_CABINETS):
        width, depth, height = rng.uniform([0.6, 0.4, 0.6], [1.4, 0.8, 1.8])
        wall = int(rng.integers(3))  # 0: y = 0, 1: y = size, 2: far wall x = size
        along = rng.uniform(3.0, size[0] - width) if wall < 2 else rng.uniform(0.5, 7.5 - width)
        if wall < 2:
            y0 = 0.0 if wall == 0 else size[1] - depth
            low, extent = [along, y0, 0.0], [width, depth, height]
        else:
            low, extent = [size[0] - depth, along, 0.0], [depth, width, height]
        lows.append(low)
        highs.append(np.add(low, extent))
    space = np.array(OBJECT_SPACE_M)
    return RoomLayout(size, np.array(lows), np.array(highs), space[:, 0], space[:, 1])


def _points_on_boxes(
    rng: np.random.Generator, lows: FloatArray, highs: FloatArray, n: int
) -> FloatArray:
    """Return n points uniform on the side and top faces of boxes (B, 3), area-weighted."""
    extent = highs - lows
    faces = [(b, axis, side) for b in range(len(lows)) for axis in range(3) for side in (0, 1)]
    faces = [f for f in faces if not (f[1] == 2 and f[2] == 0)]  # no bottom faces
    areas = np.array([np.prod(np.delete(extent[b], axis)) for b, axis, _ in faces])
    chosen = rng.choice(len(faces), size=n, p=areas / areas.sum())
    boxes = [faces[c][0] for c in chosen]
    points = lows[boxes] + rng.random((n, 3)) * extent[boxes]
    for row, c in enumerate(chosen):
        b, axis, side = faces[c]
        points[row, axis] = highs[b, axis] if side else lows[b, axis]
    return np.asarray(points, dtype=np.float64)


def sample_static_points(rng: np.random.Generator, room: RoomLayout, n: int) -> FloatArray:
    """Return n static points (n, 3) m on the walls, floor, ceiling and cabinets."""
    sx, sy, sz = room.size_m
    counts = [int(f * n) for f in _SURFACE_FRACTIONS]
    fixed = ((0, sx), (1, 0.0), (1, sy), (2, 0.0), (2, sz))
    parts = []
    for count, (axis, value) in zip(counts, fixed, strict=True):
        points = rng.random((count, 3)) * room.size_m
        points[:, axis] = value
        parts.append(points)
    parts.append(_points_on_boxes(rng, room.cabinets_min_m, room.cabinets_max_m, n - sum(counts)))
    return np.vstack(parts)


def sample_loop_wall(
    rng: np.random.Generator, room: RoomLayout, origin_m: FloatArray, yaw_rad: float, n: int
) -> FloatArray:
    """Return n points (n, 3) m on the wall a camera at ``origin_m`` faces at ``yaw_rad``."""
    size = room.size_m
    direction = np.array([np.cos(yaw_rad), np.sin(yaw_rad)])
    best_t, best_axis = np.inf, 0
    for axis in range(2):
        if abs(direction[axis]) < 1e-12:
            continue
        wall = size[axis] if direction[axis] > 0 else 0.0
        t = (wall - origin_m[axis]) / direction[axis]
        if 0.0 < t < best_t:
            best_t, best_axis = t, axis
    hit = origin_m[:2] + best_t * direction
    along = 1 - best_axis  # the wall runs along the other horizontal axis
    low = max(0.0, hit[along] - _LOOP_PATCH_HALF_WIDTH_M)
    high = min(size[along], hit[along] + _LOOP_PATCH_HALF_WIDTH_M)
    points = np.empty((n, 3))
    points[:, best_axis] = size[best_axis] if direction[best_axis] > 0 else 0.0
    points[:, along] = rng.uniform(low, high, n)
    points[:, 2] = rng.uniform(0.0, size[2], n)
    return points
