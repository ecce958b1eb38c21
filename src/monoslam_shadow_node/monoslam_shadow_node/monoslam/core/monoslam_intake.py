"""Which tracks enter MonoSLAM's map in a frame (``MonoSlam._add_features``).

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig
from slam_core.arrays import FloatArray


def wanted(
    config: MonoSlamConfig, offered: int, measured: int, cleared: int, trusted: int
) -> tuple[int, int]:
    """Return how many handovers and how many undecided or new features a frame adds."""
    target = config.target_measured
    if config.initialize != 'handover':
        return 0, min(config.max_new_per_frame, max(0, target - measured))
    waiting = config.undecided_probation  # fills wait on probation?
    take = min(offered, max(0, target - (cleared if waiting else measured)))
    if not config.fill_undecided:
        return take, 0
    taken_fix = 0 if config.handover_probation else take  # handovers fixing the camera
    fixing = measured + take if waiting else trusted + taken_fix
    return take, min(config.max_new_per_frame, max(0, target - fixing))


def farthest_first(
    pixels: FloatArray,
    taken: FloatArray,
    budget: int,
    min_spacing_px: float,
    insert: Callable[[int], bool],
) -> list[int]:
    """Insert candidates ``pixels`` (N, 2) farthest from ``taken`` (M, 2) first; return indices."""
    gap = np.full(len(pixels), np.inf)
    if len(taken):
        gap = np.min(np.linalg.norm(pixels[:, None] - taken[None], axis=2), axis=1)
    inserted: list[int] = []
    while len(inserted) < budget:
        best = int(np.argmax(gap))
        if gap[best] < min_spacing_px:
            break
        gap[best] = -1.0
        if insert(best):
            inserted.append(best)
            gap = np.minimum(gap, np.linalg.norm(pixels - pixels[best], axis=1))
    return inserted


def handover_inverse_depth(
    position: FloatArray, covariance: FloatArray, centre: FloatArray, prior_variance: float
) -> tuple[float, float] | None:
    """Return (rho 1/m, variance) of a handover at ``position`` (3,) seen from ``centre`` (3,)."""
    offset = position - centre
    depth = float(np.linalg.norm(offset))
    if depth <= 1e-3:
        return None
    direction = offset / depth
    rho = 1.0 / depth
    return rho, max(float(direction @ covariance @ direction) * rho**4, prior_variance)
