"""One feature held by the Shadow filter: its status (PENDING, STATIC or DYNAMIC), its views
and the bookkeeping of its classification."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from monoslam_shadow_node.core.projective import FloatArray
from monoslam_shadow_node.core.rays import View

PENDING, STATIC, DYNAMIC = 0, 1, 2
STATUS_NAMES = {PENDING: 'PENDING', STATIC: 'STATIC', DYNAMIC: 'DYNAMIC'}


@dataclass
class Track:
    """A feature's record: id, status, first frame and stamp (int ns), its views (cleared
    once DYNAMIC), the classifier's schedule and latest statistic, missed and gated frame
    counts, the handover (point (3,) m, covariance (3, 3)) once STATIC, recent positions, and
    whether it is a suspect (SLAM revoked it after an earlier handover), and how many
    scheduled tests in a row found no static point to test (``shadow_classifier``)."""

    id: int
    status: int
    first_frame: int
    first_stamp_ns: int
    views: list[View] = field(default_factory=list)
    # per view: camera centre (N, 3), direction (N, 3), its precision (N, 3, 3) (the
    # pseudo-inverse of its covariance) and time since first sight (N,) s, for
    # shadow_classifier.predicted_visibility
    centres: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    directions: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    precisions: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    taus: FloatArray = field(default_factory=lambda: np.zeros(0))
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

    def add_view(self, view: View, precision: FloatArray) -> None:
        """Keep a view (and its arrays for the visibility prediction)."""
        self.views.append(view)
        self.centres = np.vstack([self.centres, view.centre])
        self.directions = np.vstack([self.directions, view.direction])
        self.precisions = np.concatenate([self.precisions, precision[None]])
        self.taus = np.append(self.taus, (view.stamp_ns - self.first_stamp_ns) * 1e-9)

    trajectory: list[FloatArray] = field(default_factory=list)
