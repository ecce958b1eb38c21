"""EM-SAM's settings (EmConfig) and what a run returns (EmResult, Snapshot); see
docs/design/em_sam_core.md."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from em_sam_node.core.robust_kernels import RobustKernel, cauchy_weights, huber_weights
from em_sam_node.core.sightings import Sightings
from slam_core.arrays import FloatArray, IntArray
from slam_core.params import (
    AT_LEAST_ONE,
    NON_NEGATIVE,
    POSITIVE,
    PROBABILITY,
    Range,
    check_fields,
    ruled,
)

MODES = ('paper', 'robust')
SOLVER_METHODS = ('levenberg_marquardt', 'gauss_newton')
SEED_KERNELS: dict[str, Callable[[float], RobustKernel]] = {
    'cauchy': cauchy_weights,
    'huber': huber_weights,
}


@dataclass(frozen=True)
class EmConfig:
    """EM-SAM settings. Probabilities are per landmark (test) or per sighting (gate)."""

    mode: str = ruled('robust', choices=MODES)
    lagrange_lambda: float = ruled(50.0, range=POSITIVE)
    moveable_threshold: float = ruled(0.5, range=PROBABILITY)
    max_iterations: int = ruled(20, range=AT_LEAST_ONE)
    weight_tolerance: float = ruled(1e-3, range=POSITIVE)
    false_alarm_probability: float = ruled(1e-3, range=PROBABILITY)
    gate_probability: float = ruled(1e-4, range=PROBABILITY)
    max_gated_fraction: float = ruled(0.1, range=Range(0.0, 1.0, high_open=True))
    seed_kernel: str = ruled('cauchy', choices=SEED_KERNELS)
    seed_kernel_scale: float = ruled(2.3849, range=POSITIVE)
    seed_chunk_s: float = ruled(20.0, range=POSITIVE)
    seed_growth: float = ruled(0.1, range=POSITIVE)
    solver_method: str = ruled('levenberg_marquardt', choices=SOLVER_METHODS)
    max_solver_iterations: int = ruled(50, range=AT_LEAST_ONE)
    solver_tolerance: float = ruled(1e-6, range=POSITIVE)
    estimate_noise_scale: bool = True
    max_noise_scale: float = ruled(10.0, range=Range(1.0))
    model_error_m: float = ruled(0.15, range=NON_NEGATIVE)
    final_kernel: str = ruled('cauchy', choices=('none', *SEED_KERNELS))
    final_kernel_scale: float = ruled(2.3849, range=POSITIVE)
    calibrate_odometry: bool = True

    def __post_init__(self) -> None:
        check_fields(self, prefix='EM-SAM setting ')


@dataclass(frozen=True)
class Snapshot:
    """An estimate at one stage: poses (N,3) and landmark positions (L,2) with their ids."""

    poses: FloatArray
    landmark_ids: IntArray
    landmarks: FloatArray


@dataclass(frozen=True)
class EmResult:
    """Outcome of EM-SAM over one batch: per landmark (L,) aligned with ``landmark_ids``,
    positions (L, 2) m, covariances (L, 2, 2) m^2; weight_history (T+1, L); gated (K,);
    poses (N, 3); noise_scale and final_noise_scale (2,) of range and bearing."""

    mode: str
    poses: FloatArray
    landmark_ids: IntArray
    positions: FloatArray
    covariances: FloatArray
    weights: FloatArray
    moveable: np.ndarray
    num_observations: IntArray
    weight_history: FloatArray
    gated: np.ndarray
    sightings: dict[int, Sightings]
    snapshots: dict[str, Snapshot]
    em_iterations: int
    converged: bool
    num_pieces: int
    timings_s: dict[str, float] = field(default_factory=dict)
    noise_scale: FloatArray = field(default_factory=lambda: np.ones(2))
    final_noise_scale: FloatArray = field(default_factory=lambda: np.ones(2))
    odometry_calibration: tuple[float, ...] = (1.0, 1.0)
