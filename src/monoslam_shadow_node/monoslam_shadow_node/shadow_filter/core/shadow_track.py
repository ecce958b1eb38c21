"""One feature held by the Shadow filter: status, views and classification bookkeeping."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from monoslam_shadow_node.shadow_filter.core.rays import View
from monoslam_shadow_node.shadow_filter.core.static_fit import (
    ROW_CENTRE,
    ROW_DIRECTION,
    ROW_PRECISION,
    ROW_SIZE,
    ROW_TAU,
    view_rows,
)
from slam_core.arrays import FloatArray


class Trajectory:
    """A feature's latest ``limit`` positions, amortized O(1) per position."""

    def __init__(self) -> None:
        self._points = np.zeros((0, 3))
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def append(self, point: FloatArray, limit: int) -> None:
        """Add a position (3,) m, keeping the latest ``limit``."""
        if len(self._points) != 2 * limit:
            kept = self.array(limit)
            self._points = np.zeros((2 * limit, 3))
            self._points[: len(kept)] = kept
            self._count = len(kept)
        if self._count == 2 * limit:
            self._points[: limit - 1] = self._points[self._count - limit + 1 : self._count]
            self._count = limit - 1
        self._points[self._count] = point
        self._count += 1

    def array(self, limit: int) -> FloatArray:
        """The latest ``limit`` positions (K, 3), oldest first (a copy)."""
        return self._points[max(0, self._count - limit) : self._count].copy()


@dataclass
class Track:
    """A feature's record: views, classifier schedule, counts, and once STATIC the handover
    (point (3,) m, covariance (3, 3))."""

    id: int
    status: int
    first_frame: int
    first_stamp_ns: int
    views: list[View] = field(default_factory=list)
    # per view, in the order of ``views``: the static tests' constants (``static_fit.view_rows``:
    # camera centre, direction, its precision, time since first sight, ...) in a buffer that
    # grows by doubling; ``rows`` is the part in use
    _rows: FloatArray = field(
        default_factory=lambda: np.zeros((0, ROW_SIZE)), init=False, repr=False
    )
    _count: int = field(default=0, init=False, repr=False)
    # the first and the latest view's camera centre (3 floats), for the classifier's
    # scheduling, which runs for every pending feature in every frame
    first_centre: list[float] = field(default_factory=list, init=False, repr=False)
    last_centre: list[float] = field(default_factory=list, init=False, repr=False)
    tests_run: int = 0
    scheduled_frame: int = -1
    statistic: float = math.nan
    decided_frame: int = -1
    missed: int = 0
    gated: int = 0
    handover: tuple[FloatArray, FloatArray] | None = None
    visibility_wait: float = 0.0
    predicted_visible: float = 0.0
    milestone_due: bool = False
    suspect: bool = False
    unfit: int = 0

    def add_view(self, view: View, precision: FloatArray, row: FloatArray | None = None) -> None:
        """Keep a view with its ray precision (3, 3) and ``view_rows`` row (None: computed)."""
        if row is None:
            pose = None if view.pose_covariance is None else view.pose_covariance[None]
            row = view_rows(
                view.centre[None], view.direction[None], view.direction_covariance[None],
                np.asarray(precision, dtype=np.float64)[None], pose,
            )[0]  # fmt: skip
        if self._count == len(self._rows):
            grown = np.zeros((max(8, 2 * self._count), ROW_SIZE))
            grown[: self._count] = self._rows[: self._count]
            self._rows = grown
        self._rows[self._count] = row
        self._rows[self._count, ROW_TAU] = (view.stamp_ns - self.first_stamp_ns) * 1e-9
        self._count += 1
        self.views.append(view)
        self.last_centre = self._rows[self._count - 1, ROW_CENTRE].tolist()
        if self._count == 1:
            self.first_centre = self.last_centre

    def clear_views(self) -> None:
        """Forget the views (a DYNAMIC feature is not tested again)."""
        self.views = []
        self._rows = np.zeros((0, ROW_SIZE))
        self._count = 0
        self.first_centre, self.last_centre = [], []

    @property
    def rows(self) -> FloatArray:
        """The views' ``static_fit.view_rows`` (N, ROW_SIZE), tau filled."""
        return self._rows[: self._count]

    @property
    def centres(self) -> FloatArray:
        """Camera centres (N, 3) of the views."""
        return self._rows[: self._count, ROW_CENTRE]

    @property
    def directions(self) -> FloatArray:
        """Unit viewing directions (N, 3) of the views."""
        return self._rows[: self._count, ROW_DIRECTION]

    @property
    def precisions(self) -> FloatArray:
        """Direction precisions (N, 3, 3) of the views."""
        return self._rows[: self._count, ROW_PRECISION].reshape(-1, 3, 3)

    @property
    def taus(self) -> FloatArray:
        """Times since first sight (N,) s of the views."""
        return self._rows[: self._count, ROW_TAU]

    trajectory: Trajectory = field(default_factory=lambda: Trajectory())
