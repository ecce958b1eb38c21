"""What the EM-SAM evaluations run on replayed data, and their window and time helpers."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from em_sam_node.core.assembly import (
    MappingData,
    build_problem,
    dead_reckoning,
    initial_estimate,
    select_observations,
)
from em_sam_node.core.continuation import incremental_least_squares
from em_sam_node.core.em import run_em
from em_sam_node.core.em_types import EmConfig, EmResult
from em_sam_node.core.odometry_calibration import OdometryCalibration, estimate_calibration
from em_sam_node.core.problem import Estimate, SlamProblem
from em_sam_node.core.solver import solve
from em_sam_node.core.structure import anchor_pieces, with_weak_priors
from slam_core.arrays import FloatArray, IntArray

T = TypeVar('T')

EM_MODES = ('paper', 'robust')
FULL_RUN = 'full'
# Rounds of the calibration's M-step against the trajectory solve (``calibrate``): the
# robust mode's final solve comes after its seed's calibrations and one more M-step.
CALIBRATION_ROUNDS = 3
# Scale changes below this (0.1 %) move a 20 m stretch by 2 cm: converged.
CALIBRATION_TOLERANCE = 1e-3


@dataclass(frozen=True)
class AllStatic:
    """Plain SAM, every landmark static: poses (N,3), landmark ids (L,) and positions (L,2),
    the final cost (0.5 x squared whitened residuals, the prior included) and the runtime."""

    poses: FloatArray
    landmark_ids: IntArray
    positions: FloatArray
    cost: float
    status: str
    runtime_s: float
    calibration: OdometryCalibration = field(default_factory=OdometryCalibration)


def solve_all_static(
    data: MappingData,
    exclude: list[int] | None = None,
    *,
    incremental: bool = False,
    calibrate: bool = False,
) -> AllStatic:
    """Return plain SAM (Levenberg-Marquardt from dead reckoning) without ``exclude``;
    ``incremental``: by continuation in time; ``calibrate``: with the odometry scales."""
    started = time.perf_counter()
    solved = _solve_all_static(data, exclude, incremental)
    calibration = OdometryCalibration()
    for _ in range(CALIBRATION_ROUNDS if calibrate else 0):
        estimated = estimate_calibration(data, solved.poses)
        if np.max(np.abs(estimated.parameters - calibration.parameters)) < CALIBRATION_TOLERANCE:
            break
        calibration = estimated
        solved = _solve_all_static(calibration.apply(data), exclude, False, solved.poses)
    return dataclasses.replace(
        solved, runtime_s=time.perf_counter() - started, calibration=calibration
    )


def _solve_all_static(
    data: MappingData,
    exclude: list[int] | None,
    incremental: bool,
    start_poses: FloatArray | None = None,
) -> AllStatic:
    started = time.perf_counter()
    built = build_problem(data, exclude_ids=exclude or [])
    poses0 = dead_reckoning(data) if start_poses is None else start_poses
    mapped: dict[int, FloatArray] = {}
    if incremental:
        kept = select_observations(data, ~np.isin(data.obs_landmark_id, exclude or []))

        def least_squares(problem: SlamProblem, start: Estimate) -> Estimate:
            return solve(problem, start, method='levenberg_marquardt').estimate

        poses0, mapped = incremental_least_squares(kept, least_squares)
    anchored = anchor_pieces(built.problem, poses0)
    problem = with_weak_priors(
        built.problem, anchored.extra_prior_poses, anchored.extra_prior_means
    )
    initial = (
        Estimate(poses0, np.array([mapped[int(i)] for i in built.landmark_ids.tolist()]))
        if incremental
        else initial_estimate(problem, poses0)
    )
    result = solve(problem, initial, method='levenberg_marquardt')
    return AllStatic(
        result.estimate.poses,
        built.landmark_ids,
        result.estimate.landmarks,
        result.final_cost,
        result.status,
        time.perf_counter() - started,
    )


def timed(function: Callable[[], T]) -> tuple[float, T]:
    """Return the wall time (s) of ``function()`` and its value."""
    started = time.perf_counter()
    value = function()
    return time.perf_counter() - started, value


def run_em_modes(data: MappingData) -> dict[str, tuple[float, EmResult]]:
    """Return (runtime s, result) of EM-SAM in each mode, without snapshots."""
    results = {}
    for mode in EM_MODES:
        config = EmConfig(mode=mode)
        results[mode] = timed(lambda: run_em(data, config, record_snapshots=False))  # noqa: B023
    return results


def flagged_ids(result: EmResult) -> set[int]:
    """Return the ids EM-SAM flagged moveable."""
    return {int(i) for i in result.landmark_ids[result.moveable].tolist()}


def parse_window(text: str) -> float | None:
    """Return ``--window-s`` in s (None: 'full' or 0); ValueError unless a finite number >= 0."""
    if text.strip().lower() == FULL_RUN:
        return None
    try:
        seconds = float(text)
    except ValueError:
        raise ValueError(f"time window {text!r}: give seconds (e.g. 300) or 'full'") from None
    if not math.isfinite(seconds) or seconds < 0.0:
        raise ValueError(f"time window {text!r}: must be a finite number >= 0 or 'full'")
    return None if seconds == 0.0 else seconds


def window_label(window_s: float | None) -> str:
    """Return how a time window is named in reports: 'full' or e.g. '300 s'."""
    return FULL_RUN if window_s is None else f'{window_s:g} s'


def sightings_per_id(data: MappingData) -> dict[int, int]:
    """Return the number of sightings of every landmark id in ``data``."""
    ids, counts = np.unique(data.obs_landmark_id, return_counts=True)
    return dict(zip(ids.tolist(), counts.tolist(), strict=True))
