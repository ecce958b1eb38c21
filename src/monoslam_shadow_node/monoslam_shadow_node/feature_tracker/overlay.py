"""feature_tracker's debug image: the tracked features drawn in the colour of their latest
Shadow filter status (pending and unknown red, static blue, dynamic green; unknown hollow).

Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterable

import cv2
import numpy as np

from monoslam_shadow_node.common.conversions import MARKER_COLOURS
from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING, STATIC

UNKNOWN = -1
"""Status of an id no status message has named."""
STATUS_LABELS = {UNKNOWN: 'unknown', PENDING: 'pending', STATIC: 'static', DYNAMIC: 'dynamic'}
STATUSES_KEPT = 20000
"""The statuses of at most this many ids are remembered, the most recently named ones."""
RADIUS_PX = 4


def _bgr(status: int) -> tuple[int, int, int]:
    r, g, b = MARKER_COLOURS[PENDING if status == UNKNOWN else status]
    return round(255 * b), round(255 * g), round(255 * r)


class StatusBook:
    """The latest status of each track id heard of, for at most ``capacity`` ids."""

    def __init__(self, capacity: int = STATUSES_KEPT) -> None:
        if capacity <= 0:
            raise ValueError(f'capacity={capacity!r}: must be > 0')
        self.capacity = capacity
        self._status: OrderedDict[int, int] = OrderedDict()

    def __len__(self) -> int:
        return len(self._status)

    def update(self, entries: Iterable[tuple[int, int]]) -> int:
        """Record (id, status) pairs (other statuses ignored); return how many."""
        recorded = 0
        for track_id, status in entries:
            if status not in (PENDING, STATIC, DYNAMIC):
                continue
            self._status[int(track_id)] = int(status)
            self._status.move_to_end(int(track_id))
            recorded += 1
        while len(self._status) > self.capacity:
            self._status.popitem(last=False)
        return recorded

    def status(self, track_id: int) -> int:
        """Return the id's latest status, or UNKNOWN."""
        return self._status.get(int(track_id), UNKNOWN)


def draw_features(
    image: np.ndarray, ids: np.ndarray, pixels: np.ndarray, book: StatusBook
) -> tuple[np.ndarray, dict[str, int]]:
    """Return a BGR copy of ``image`` ((H, W) or (H, W, 3) uint8) with features ``ids`` (N,)
    at ``pixels`` (N, 2) drawn in status colours, and the count per status name."""
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    counts = dict.fromkeys(STATUS_LABELS.values(), 0)
    for track_id, (u, v) in zip(ids.tolist(), np.asarray(pixels).reshape(-1, 2), strict=True):
        status = book.status(track_id)
        counts[STATUS_LABELS[status]] += 1
        centre = (round(float(u)), round(float(v)))
        thickness = 1 if status == UNKNOWN else -1
        cv2.circle(canvas, centre, RADIUS_PX, _bgr(status), thickness, cv2.LINE_AA)
    legend = '  '.join(f'{name} {count}' for name, count in counts.items())
    cv2.putText(canvas, legend, (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3)
    cv2.putText(canvas, legend, (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
    return canvas, counts
