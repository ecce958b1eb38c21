"""Camera pose errors shared between images: what the all-view static test needs from them.

A SLAM filter's pose errors are not independent from image to image: its estimate drifts,
and the error of one image's pose is mostly an earlier image's (docs/design/shadow_filter.md,
section 1). A pose source that knows this says so with each pose: the covariances
Cov(e_now, e_then) of this pose's error with those of its recent earlier poses, by their
stamps (6 x 6 each, over position and rotation about the world axes, as the pose covariance;
``MonoSlamResult.pose_cross_covariances``, carried exactly by the EKF). Each view keeps its
frame's table (``View.pose_cross``), so the errors of a feature's views have the covariance

    Cov(e_j, e_i) = view j's entry for view i's stamp    (i < j),

The test uses the views the latest view's table covers (``covered_views``; a source without
tables: all views, their errors independent, as before). Cutting the table off instead
(taking views further apart than the source remembers as independent) does not give a
covariance: see ``monoslam_state.POSE_HISTORY``.

What the static test does with it (``view_fit``, generalized least squares):

- the residuals' covariance between views i and j gains J_i Cov(e_i, e_j) J_j', J the
  residual's Jacobian with respect to the pose (``cross_blocks``);
- the exact Jacobian of the angular residual with respect to the point,
  (B_i' - r_i d_i') / rho_i, carries the residual itself, and with it the camera centre's
  error; the residual there is replaced by its expected part without that error,
  r - Sigma_C Sigma^-1 r (Sigma_C the covariance of the centre errors' part of the
  residuals with the residuals, rotation errors tied to the centre's included: SLAM's
  are, strongly; ``centre_free_residuals``). Without it the score test of a static point
  seen from 3 cm centre errors at 4 m gives a median T of 51 for a chi-square(3); with it
  and the shared errors declared, 2.5-3.0 whether the errors are independent or correlated
  over 10 or 100 images (the Monte Carlo of ``test_pose_links``).
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
    """Return a frame's table {earlier stamp: Cov(e_now, e_then) (6, 6)} from the source's
    stamps (K,) and covariances (K, 6, 6) (None or empty: no table)."""
    if covariances is None or not len(stamps):
        return {}
    return {int(stamp): covariances[k] for k, stamp in enumerate(stamps)}


def covered_views(views: Sequence[V]) -> list[V]:
    """Return the views (in stamp order) whose pose errors the latest view's table covers,
    and the latest: any two of them are covered by the later one's (the source remembers
    every recent pose and every k-th older one, ``monoslam_state.POSE_HISTORY``). All views
    when the latest has no table."""
    table = views[-1].pose_cross if views else None
    if not table:
        return list(views)
    return [view for view in views[:-1] if view.stamp_ns in table] + [views[-1]]


def pose_covariances_between(
    stamps: Sequence[int],
    covariances: Sequence[FloatArray | None],
    tables: Sequence[Mapping[int, FloatArray] | None],
) -> FloatArray | None:
    """Return Cov(e_j, e_i) (N, N, 6, 6) of the pose errors of N views in stamp order from
    their stamps, covariances (None: a known pose, no error) and tables (``cross_table``);
    None when no table holds another view's stamp (the errors are independent: the
    diagonal alone, which the caller has)."""
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
    """Return J_j Cov(e_j, e_i) K_i' (N, N, m, m) for the views' pose errors ``between``
    (N, N, k, l) seen through the Jacobians J (N, m, k) and K (N, m, l) (default J) of
    residuals with respect to them."""
    seen = jacobians[:, None] @ between  # batched products: einsum's are 3x slower here
    other = jacobians if right is None else right
    return np.asarray(seen @ np.swapaxes(other, 1, 2)[None], dtype=np.float64)


def centre_free_residuals(
    residuals: FloatArray, centre_blocks: FloatArray, solve: FloatArray
) -> FloatArray:
    """Return r - Sigma_C Sigma^-1 r (N, 2) for residuals (N, 2), the covariance of the
    centre errors' part of them with them all ``centre_blocks`` (N, N, 2, 2) and ``solve`` =
    Sigma^-1 r (2N,)."""
    count = len(residuals)
    share = centre_blocks.transpose(0, 2, 1, 3).reshape(2 * count, 2 * count) @ solve
    return np.asarray(residuals - share.reshape(count, 2), dtype=np.float64)
