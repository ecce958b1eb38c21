"""The planar SAM problem as arrays: poses x_i = (x, y, theta), landmarks l_j = (x, y).

Conventions (SI units, map frame): pose index i in [0, num_poses), landmark index j in
[0, num_landmarks) (dense indices; the caller maps landmark ids to them). Noise enters as
square-root information matrices W (upper triangular, W^T W = Sigma^-1), so a whitened
residual is W @ (measured - predicted), with angles wrapped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import FloatArray, IntArray


@dataclass(frozen=True)
class SlamProblem:
    """Factors of one planar SAM problem.

    Odometry factor m (the paper's eq. 1-2) links pose ``odometry_from[m]`` to
    ``odometry_to[m]`` with increment ``odometry_u[m] = (u0 forward m, u1 side m, u2 rad)``:
    x_to = x_from + [u0 cos(t~) - u1 sin(t~), u0 sin(t~) + u1 cos(t~), u2], t~ = theta_from + u2/2.
    Observation k (eq. 3) of landmark ``obs_landmark[k]`` from pose ``obs_pose[k]`` measures
    ``obs_z[k] = (range m, bearing rad)``. The prior anchors pose ``prior_pose_index``.

    ``odometry_model`` ``'se2_between'`` reads ``odometry_u[m]`` instead as a measured
    relative pose (dx m, dy m, dtheta rad) in the frame of pose ``odometry_from[m]``, with
    GTSAM's BetweenFactor<Pose2> error Log(u^-1 x_from^-1 x_to), for data recorded that way
    (the Victoria Park file) and for side-by-side comparisons with GTSAM.

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
    """Outcome of a nonlinear least-squares solve.

    ``cost_history[i]`` is 0.5 * ||whitened residual||^2 after accepted step i (index 0 is
    the initial cost); ``status`` says why it stopped.
    """

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
