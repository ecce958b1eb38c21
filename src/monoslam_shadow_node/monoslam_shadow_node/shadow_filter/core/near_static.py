"""The depth a static fit may have: a feature's all-view static fit is handed over only where
its inverse depth is plausible under the prior every feature starts with in the Shadow
filter's EKF (``EkfConfig.initial_inverse_depth_per_m`` and its sigma, the inverse distance
along the viewing ray); nearer, it waits for more views. Why (a mover against a camera that
moves straight has rays that meet near the lens) and the figures: docs/design/shadow_filter.md,
section 5."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from monoslam_shadow_node.shadow_filter.core.rays import View
from slam_core.arrays import FloatArray
from slam_core.lazy_stats import norm

WAIT_WARNING = 'nearer than the depth prior allows'
"""In the warning of a static fit that waits (``shadow_decision.decide``; counted by the
shadow_filter node)."""


def implausibly_near(
    point: FloatArray, views: Sequence[View], prior: tuple[float, float], alpha: float
) -> float | None:
    """Return the distance (m) along the viewing ray of ``point`` (3,) from the nearer of the
    first and the latest of ``views`` when that is not in front of the camera or its inverse
    is beyond the ``prior`` (mean, sigma; per m) at level ``alpha`` (one-sided: mean plus the
    normal quantile times sigma); None when it is plausible (or there are no views)."""
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
