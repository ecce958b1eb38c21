"""The planar SAM problem as arrays: poses (x, y, theta), landmarks (x, y), SI units, map
frame; see docs/design/em_sam_core.md."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import FloatArray, IntArray


@dataclass(frozen=True)
class SlamProblem:
    """Factors of one planar SAM problem (eq. 1-3) with square-root informations.

    Shapes: odometry_* (M,), (M, 3), (M, 3, 3); obs_* (K,), (K,), (K, 2), (K, 2, 2);
    prior_mean (3,), prior_sqrt_info (3, 3).
    """

    num_poses: int
    num_landmarks: int
    odometry_from: IntArray
    odometry_to: IntArray
    odometry_u: FloatArray
    odometry_sqrt_info: FloatArray
    obs_pose: IntArray
    obs_landmark: IntArray
    obs_z: FloatArray
    obs_sqrt_info: FloatArray
    prior_mean: FloatArray
    prior_sqrt_info: FloatArray
    prior_pose_index: int = 0
    fixed_landmarks: NDArray[np.bool_] | None = None
    odometry_model: str = 'differential_drive'

    # ``fixed_landmarks`` (L,) marks landmarks held at their initial value: their
    # observations constrain the poses only (a known map, e.g. in a sliding-window solve).

    @property
    def num_odometry(self) -> int:
        """M, the number of odometry factors."""
        return int(self.odometry_from.shape[0])

    @property
    def num_observations(self) -> int:
        """K, the number of range-bearing factors."""
        return int(self.obs_pose.shape[0])


@dataclass
class Estimate:
    """Values of all variables: poses (N, 3) as (x m, y m, theta rad), landmarks (L, 2) m."""

    poses: FloatArray
    landmarks: FloatArray

    def copy(self) -> Estimate:
        """Return a deep copy."""
        return Estimate(self.poses.copy(), self.landmarks.copy())


@dataclass(frozen=True)
class SolveResult:
    """Outcome of a nonlinear least-squares solve: estimate, cost history, status."""

    estimate: Estimate
    cost_history: tuple[float, ...]
    iterations: int
    converged: bool
    status: str
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def final_cost(self) -> float:
        """Cost at the returned estimate."""
        return self.cost_history[-1]
