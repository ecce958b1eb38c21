"""Where monoslam's known points come from besides a marker: 'depth' or 'file' (ROS-free).

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import csv
import math
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monoslam_shadow_node.common.core.inputs import Features
from monoslam_shadow_node.monoslam.core.monoslam_init import MIN_KNOWN_POINTS
from slam_core.arrays import FloatArray

DEPTH_IMAGES_KEPT = 30
"""Depth images held for pairing while the filter waits (about 1 s at 30 Hz)."""


@dataclass(frozen=True, eq=False)
class DepthImage:
    """Depth on the colour camera's grid: stamp (ns), frame, depth (H, W) m (NaN, 0: none)."""

    stamp_ns: int
    frame_id: str
    depth_m: FloatArray


class DepthStart:
    """Pairs feature frames with depth images while the filter waits (module docstring)."""

    def __init__(self, tolerance_ns: int, horizon_ns: int, queue_size: int) -> None:
        self.tolerance_ns = tolerance_ns
        self.horizon_ns = horizon_ns
        self.frames: deque[Features] = deque(maxlen=queue_size)
        self.depths: deque[DepthImage] = deque(maxlen=DEPTH_IMAGES_KEPT)

    def add_depth(self, image: DepthImage) -> bool:
        """Hold a depth image; False (not held) for one not newer than the newest held."""
        if self.depths and image.stamp_ns <= self.depths[-1].stamp_ns:
            return False
        self.depths.append(image)
        return True

    def next(self, flush: bool = False) -> tuple[Features, DepthImage | None] | None:
        """Return the oldest held frame and its depth (None: cannot pair), or None while it may."""
        if not self.frames:
            return None
        frame = self.frames[0]
        depth = self._nearest(frame.stamp_ns)
        newest_depth = self.depths[-1].stamp_ns if self.depths else None
        late = newest_depth is not None and newest_depth > frame.stamp_ns + self.tolerance_ns
        stale = self.frames[-1].stamp_ns - frame.stamp_ns > self.horizon_ns
        if depth is None and not (late or stale or flush):
            return None
        return self.frames.popleft(), depth

    def _nearest(self, stamp_ns: int) -> DepthImage | None:
        best = min(self.depths, key=lambda d: abs(d.stamp_ns - stamp_ns), default=None)
        if best is None or abs(best.stamp_ns - stamp_ns) > self.tolerance_ns:
            return None
        return best


@dataclass(frozen=True, eq=False)
class KnownPointRows:
    """Known points from a file: keys (K,), world positions (K, 3) m, first-image pixels (K, 2)."""

    keys: np.ndarray
    positions_m: FloatArray
    pixels: FloatArray

    def known_points(self) -> dict[int, tuple[float, float, float]]:
        """Return them as the filter's known points (key -> world point)."""
        return {
            int(k): (float(x), float(y), float(z))
            for k, (x, y, z) in zip(self.keys, self.positions_m, strict=True)
        }


def read_known_points(path: Path) -> KnownPointRows:
    """Read ``id,x,y,z,u,v`` rows after a header; ValueError naming the file and line."""
    try:
        text = Path(path).read_text(encoding='utf-8')
    except OSError as error:
        raise ValueError(f'known points file {path}: {error.strerror or error}') from error
    reader = csv.reader(text.splitlines())
    header = next(reader, None)
    expected = ['id', 'x', 'y', 'z', 'u', 'v']
    if header is None or [h.strip() for h in header] != expected:
        raise ValueError(f'{path}:1: header must be {",".join(expected)}, got {header}')
    keys: list[int] = []
    values: list[list[float]] = []
    for line, row in enumerate(reader, start=2):
        if not row or not ''.join(row).strip():
            continue
        try:
            if len(row) != 6:
                raise ValueError(f'{len(row)} columns, expected 6')
            key, numbers = int(row[0]), [float(v) for v in row[1:]]
        except ValueError as error:
            raise ValueError(f'{path}:{line}: {error}') from error
        if not all(math.isfinite(v) for v in numbers):
            raise ValueError(f'{path}:{line}: values must be finite, got {row[1:]}')
        if key in keys:
            raise ValueError(f'{path}:{line}: id {key} given twice')
        keys.append(key)
        values.append(numbers)
    if len(keys) < MIN_KNOWN_POINTS:
        raise ValueError(f'{path}: {len(keys)} known points, at least {MIN_KNOWN_POINTS} needed')
    array = np.array(values, dtype=np.float64)
    return KnownPointRows(np.array(keys, dtype=np.int64), array[:, :3], array[:, 3:])


def assign_known_points(
    rows: KnownPointRows, features: Features, match_px: float
) -> dict[int, int]:
    """Return track id -> known key for rows with a track within ``match_px`` (one to one)."""
    if not len(features.ids):
        return {}
    distances = np.linalg.norm(rows.pixels[:, None, :] - features.pixels[None, :, :], axis=2)
    pairs = sorted(
        (float(distances[r, t]), r, t)
        for r, t in zip(*np.nonzero(distances <= match_px), strict=True)
    )
    taken_rows: set[int] = set()
    assigned: dict[int, int] = {}
    for _, r, t in pairs:
        track = int(features.ids[t])
        if r in taken_rows or track in assigned:
            continue
        taken_rows.add(r)
        assigned[track] = int(rows.keys[r])
    return assigned
