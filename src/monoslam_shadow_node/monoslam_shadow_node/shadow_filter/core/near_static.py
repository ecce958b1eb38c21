"""Whether a static fit lies nearer than the EKF's inverse-depth prior allows (then it waits).

Why and the figures: docs/design/shadow_filter.md, section 5."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from monoslam_shadow_node.shadow_filter.core.rays import View
from slam_core.arrays import FloatArray
from slam_core.lazy_stats import norm

WAIT_WARNING = 'nearer than the depth prior allows'
"""In the warning of a static fit that waits (counted by the processor)."""


def implausibly_near(
    point: FloatArray, views: Sequence[View], prior: tuple[float, float], alpha: float
) -> float | None:
    """Return the distance (m) of ``point`` (3,) along the nearer of the first and last
    views' rays when implausible under ``prior`` (mean, sigma; 1/m) at ``alpha``, else None."""
    if not views:
        return None
    distance = min(
        float(np.dot(np.asarray(point, np.float64) - view.centre, view.direction))
        for view in (views[0], views[-1])
    )
    mean, sigma = prior
    if distance > 0.0 and 1.0 / distance <= mean + float(norm.isf(alpha)) * sigma:
        return None
    return distance
