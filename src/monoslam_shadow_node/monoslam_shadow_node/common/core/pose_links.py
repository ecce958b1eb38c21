"""Camera pose errors shared between images, for the all-view static test.

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Protocol, TypeVar

import numpy as np

from slam_core.arrays import FloatArray

POSE_DOF = 6
CENTRE = slice(0, 3)


class _Posed(Protocol):
    @property
    def stamp_ns(self) -> int: ...

    @property
    def pose_cross(self) -> Mapping[int, FloatArray] | None: ...


V = TypeVar('V', bound=_Posed)


def cross_table(stamps: Sequence[int], covariances: FloatArray | None) -> dict[int, FloatArray]:
    """Return {earlier stamp: Cov(e_now, e_then) (6, 6)} from stamps (K,) and (K, 6, 6)."""
    if covariances is None or not len(stamps):
        return {}
    return {int(stamp): covariances[k] for k, stamp in enumerate(stamps)}


def covered_views(views: Sequence[V]) -> list[V]:
    """Return the views (stamp order) the latest view's table covers, and the latest."""
    table = views[-1].pose_cross if views else None
    if not table:
        return list(views)
    return [view for view in views[:-1] if view.stamp_ns in table] + [views[-1]]


def pose_covariances_between(
    stamps: Sequence[int],
    covariances: Sequence[FloatArray | None],
    tables: Sequence[Mapping[int, FloatArray] | None],
) -> FloatArray | None:
    """Return Cov(e_j, e_i) (N, N, 6, 6) of N views' pose errors; None when all independent."""
    count = len(stamps)
    blocks = np.zeros((count, count, POSE_DOF, POSE_DOF))
    shared = False
    for j in range(count):
        covariance, table = covariances[j], tables[j]
        if covariance is None:
            continue
        blocks[j, j] = covariance
        if not table:
            continue
        for i in range(j):
            entry = table.get(stamps[i])
            if entry is not None and covariances[i] is not None:
                blocks[j, i] = entry
                blocks[i, j] = entry.T
                shared = True
    return blocks if shared else None


def cross_blocks(
    between: FloatArray, jacobians: FloatArray, right: FloatArray | None = None
) -> FloatArray:
    """Return J_j Cov(e_j, e_i) K_i' (N, N, m, m); J (N, m, k), K (N, m, l) (default J)."""
    seen = jacobians[:, None] @ between  # batched products: einsum's are 3x slower here
    other = jacobians if right is None else right
    return np.asarray(seen @ np.swapaxes(other, 1, 2)[None], dtype=np.float64)


def centre_free_residuals(
    residuals: FloatArray, centre_blocks: FloatArray, solve: FloatArray
) -> FloatArray:
    """Return r - Sigma_C Sigma^-1 r (N, 2); ``centre_blocks`` (N, N, 2, 2), ``solve`` (2N,)."""
    count = len(residuals)
    share = centre_blocks.transpose(0, 2, 1, 3).reshape(2 * count, 2 * count) @ solve
    return np.asarray(residuals - share.reshape(count, 2), dtype=np.float64)
