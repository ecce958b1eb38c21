"""Which tracks enter MonoSLAM's map in a frame (``MonoSlam._add_features``): how many
handovers and new or undecided features the frame takes (``wanted``), where the new ones go
(``farthest_first``), and the inverse depth a handover enters with
(``handover_inverse_depth``)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig
from slam_core.arrays import FloatArray


def wanted(
    config: MonoSlamConfig, offered: int, measured: int, cleared: int, trusted: int
) -> tuple[int, int]:
    """Return how many handovers and how many undecided or new features a frame adds, given
    the handovers observed in it (``offered``) and the features measured, measured and
    cleared, and measured and trusted (counts): handovers while fewer than
    ``target_measured`` features were measured (cleared ones with ``undecided_probation``),
    and new or undecided features, up to ``max_new_per_frame``, while fewer than that fix the
    camera (all measured ones with ``undecided_probation``), counting the handovers taken."""
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
    """Offer candidates (``pixels`` (N, 2)) to ``insert`` (index -> whether it went in) where
    the measured features (``taken`` (M, 2)) and those inserted so far leave the largest
    gap, until ``budget`` went in or the largest gap is below ``min_spacing_px``; return the
    indices inserted."""
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
    """Return the inverse depth (1/m) and its variance that a point handed over at
    ``position`` (3,) m with ``covariance`` (3, 3) enters with, seen from the camera centre
    ``centre`` (3,): the variance at least the prior's (triangulated from SLAM's poses, the
    point is not independent of them); None for a point at the centre."""
    offset = position - centre
    depth = float(np.linalg.norm(offset))
    if depth <= 1e-3:
        return None
    direction = offset / depth
    rho = 1.0 / depth
    return rho, max(float(direction @ covariance @ direction) * rho**4, prior_variance)
