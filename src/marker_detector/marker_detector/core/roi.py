"""Where to look for markers in the next frame: the whole image, or boxes about the markers
of the frame before. Design notes: docs/design/marker_core.md"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slam_core.arrays import FloatArray

SIDE_SHARE = 0.25

Box = tuple[int, int, int, int]
"""A search region: x0, y0, x1, y1 px (x1, y1 exclusive) in the image."""


@dataclass
class SearchPlan:
    """The whole image every ``period`` frames; between them, boxes grown by ``margin_px`` (px)
    about the markers followed."""

    period: int = 1
    margin_px: float = 32.0
    wanted: frozenset[int] = frozenset()  # the only ids looked for (empty: any id)
    followed: dict[int, FloatArray] = field(default_factory=dict)  # id -> corners (4, 2)
    since_full: int = 0  # frames since the last whole-image search
    last_stamp_ns: int | None = None
    full_searches: int = 0
    box_searches: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.period, int) or isinstance(self.period, bool) or self.period < 1:
            raise ValueError(f'search period {self.period!r} must be an int >= 1 (frames)')
        if not (math.isfinite(self.margin_px) and self.margin_px >= 0.0):
            raise ValueError(f'search margin {self.margin_px!r} must be a finite number >= 0 px')

    def boxes(self, stamp_ns: int, shape: tuple[int, ...]) -> list[Box] | None:
        """Return the boxes to search in the frame at ``stamp_ns`` of ``shape`` (H, W, ...), or
        None for the whole image."""
        if self.last_stamp_ns is not None and stamp_ns <= self.last_stamp_ns:
            self.reset()
        self.last_stamp_ns = stamp_ns
        if self.period == 1 or not self.followed:
            return None
        if self.since_full + 1 >= self.period and not self.follows_every_wanted_id:
            return None
        height, width = shape[0], shape[1]
        boxes = [self._box(corners, width, height) for corners in self.followed.values()]
        return merge_boxes([b for b in boxes if b[2] > b[0] and b[3] > b[1]])

    @property
    def follows_every_wanted_id(self) -> bool:
        """Whether only given ids are looked for and each of them is followed."""
        return bool(self.wanted) and self.wanted <= set(self.followed)

    def needs_full_search(self, found: set[int]) -> bool:
        """Whether a box search that found the ids ``found`` missed a followed marker."""
        return not set(self.followed) <= found

    def searched(self, full: bool, markers: dict[int, FloatArray]) -> None:
        """Record a frame's search (whole or boxes) and the markers (id -> corners) to follow."""
        if full:
            self.full_searches += 1
            self.since_full = 0
        else:
            self.box_searches += 1
            self.since_full += 1
        self.followed = dict(markers) if self.period > 1 else {}

    def reset(self) -> None:
        """Forget the followed markers (a new camera or a new run)."""
        self.followed = {}
        self.since_full = 0
        self.last_stamp_ns = None

    def _box(self, corners: FloatArray, width: int, height: int) -> Box:
        low, high = corners.min(axis=0), corners.max(axis=0)
        grow = self.margin_px + SIDE_SHARE * float(np.max(high - low))
        x0, y0 = (max(0, math.floor(v - grow)) for v in low)
        x1 = min(width, math.ceil(float(high[0]) + grow) + 1)
        y1 = min(height, math.ceil(float(high[1]) + grow) + 1)
        return int(x0), int(y0), int(x1), int(y1)


def merge_boxes(boxes: list[Box]) -> list[Box]:
    """Return the boxes with each overlapping pair replaced by the box round both."""
    merged = list(boxes)
    changed = True
    while changed:
        changed = False
        for i in range(len(merged)):
            for j in range(i + 1, len(merged)):
                a, b = merged[i], merged[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    merged[i] = (
                        min(a[0], b[0]),
                        min(a[1], b[1]),
                        max(a[2], b[2]),
                        max(a[3], b[3]),
                    )
                    del merged[j]
                    changed = True
                    break
            if changed:
                break
    return merged
