"""GTSAM graphs of the benchmarks' MRCLAM runs, on fixed grids so that GTSAM sees the same
numbers whatever last bits our float pipeline produced.

Why the grids: GNC-TLS decides per sighting, by a threshold, whether it is an inlier, and
the decisions feed the next solve; on MRCLAM data set 6 robot 1 (full run) a relative change
of 1e-15 in the odometry increments moved its ATE between 0.11 and 0.50 m (measured:
bench/README.md). Refactors that reorder float operations, and numpy's SIMD paths on other
CPUs, change last bits; so every number handed to GTSAM is rounded first: positions, angles
and the odometry's relative poses to an absolute grid of 2^-30 (about 1e-9 m or rad, far
below the data's millimetre resolution and far above double round-off on values of a few
metres), standard deviations to 30 mantissa bits (about 9 digits) and correlations to the
absolute 2^-30 grid. A value then changes on the grid only if round-off moves it across a
grid boundary: about 1e-16 / 1e-9 per value, 2e-3 for a run's ~2e4 values.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from em_sam_node.core.assembly import (
    BuiltProblem,
    MappingData,
    build_problem,
    dead_reckoning,
    initial_estimate,
)
from em_sam_node.core.incremental_parts import between_of_increment

GRID_BITS = 30  # grid 2^-30: ~9.3e-10 absolute (m, rad, correlation), 9 digits relative


def on_grid(values: Any) -> np.ndarray:
    """Return ``values`` rounded to multiples of 2^-GRID_BITS (exact in binary floats)."""
    scale = float(2**GRID_BITS)
    rounded: np.ndarray = np.round(np.asarray(values, dtype=np.float64) * scale) / scale
    return rounded


def relative_grid(values: Any) -> np.ndarray:
    """Return positive ``values`` with their mantissas rounded to GRID_BITS bits."""
    mantissa, exponent = np.frexp(np.asarray(values, dtype=np.float64))
    rounded: np.ndarray = np.ldexp(on_grid(mantissa), exponent)
    return rounded


def covariance_on_grid(covariance: np.ndarray) -> np.ndarray:
    """Return covariances (..., n, n) with standard deviations on the relative grid and
    correlations on the absolute grid (symmetric by construction)."""
    cov = 0.5 * (covariance + np.swapaxes(covariance, -1, -2))
    sigma = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))
    outer = sigma[..., :, None] * sigma[..., None, :]
    correlation = on_grid(cov / outer)
    sigma = relative_grid(sigma)
    gridded: np.ndarray = correlation * (sigma[..., :, None] * sigma[..., None, :])
    return gridded


@dataclass(frozen=True)
class Graph:
    """A run's factor graph and start in GTSAM: keys i (pose i) and symbol('l', j)
    (landmark index j of ``built``); factor 0 is the prior, 1..M the odometry, then one
    bearing-range factor per observation of ``built.problem``."""

    graph: Any
    values: Any
    built: BuiltProblem
    first_observation: int


def mrclam_graph(gtsam: Any, data: MappingData, exclude: list[int] | None = None) -> Graph:
    """Return the factors of ``data`` (without the landmarks in ``exclude``) and the
    dead-reckoning start (landmarks from their first sighting), every number on the grids."""
    built = build_problem(data, exclude_ids=exclude or [])
    problem = built.problem
    start = initial_estimate(problem, dead_reckoning(data))
    noise = gtsam.noiseModel
    graph = gtsam.NonlinearFactorGraph()
    graph.add(
        gtsam.PriorFactorPose2(
            0,
            gtsam.Pose2(*on_grid(data.prior_pose)),
            noise.Gaussian.Covariance(covariance_on_grid(data.prior_cov)),
        )
    )
    between, cov = between_of_increment(data.odometry_u, data.odometry_cov)
    between, cov = on_grid(between), covariance_on_grid(cov)
    for m in range(len(between)):
        graph.add(
            gtsam.BetweenFactorPose2(
                int(data.odometry_from[m]),
                int(data.odometry_to[m]),
                gtsam.Pose2(*between[m]),
                noise.Gaussian.Covariance(cov[m]),
            )
        )
    first_observation = graph.size()
    obs_cov = data.obs_cov[built.observation_rows]
    sigmas = relative_grid(np.sqrt(np.column_stack([obs_cov[:, 1, 1], obs_cov[:, 0, 0]])))
    z = on_grid(problem.obs_z)
    for k in range(problem.num_observations):
        graph.add(
            gtsam.BearingRangeFactor2D(
                int(problem.obs_pose[k]),
                gtsam.symbol('l', int(problem.obs_landmark[k])),
                gtsam.Rot2(float(z[k, 1])),
                float(z[k, 0]),
                noise.Diagonal.Sigmas(sigmas[k]),
            )
        )
    values = gtsam.Values()
    for i, pose in enumerate(on_grid(start.poses)):
        values.insert(i, gtsam.Pose2(*pose))
    for j, point in enumerate(on_grid(start.landmarks)):
        values.insert(gtsam.symbol('l', j), point)
    return Graph(graph, values, built, first_observation)


def poses_of(values: Any, num_poses: int) -> np.ndarray:
    """Return the poses (N,3) of gtsam.Values with keys 0..N-1."""
    return np.array([[(p := values.atPose2(i)).x(), p.y(), p.theta()] for i in range(num_poses)])
