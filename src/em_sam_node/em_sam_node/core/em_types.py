"""EM-SAM's settings (EmConfig) and what a run returns (EmResult, Snapshot); see
docs/design/em_sam_core.md."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from em_sam_node.core.robust_kernels import RobustKernel, cauchy_weights, huber_weights
from em_sam_node.core.sightings import Sightings
from slam_core.arrays import FloatArray, IntArray

MODES = ('paper', 'robust')
SEED_KERNELS: dict[str, Callable[[float], RobustKernel]] = {
    'cauchy': cauchy_weights,
    'huber': huber_weights,
}


@dataclass(frozen=True)
class EmConfig:
    """EM-SAM settings. Probabilities are per landmark (test) or per sighting (gate)."""

    mode: str = 'robust'
    lagrange_lambda: float = 50.0
    moveable_threshold: float = 0.5
    max_iterations: int = 20
    weight_tolerance: float = 1e-3
    false_alarm_probability: float = 1e-3
    gate_probability: float = 1e-4
    max_gated_fraction: float = 0.1
    seed_kernel: str = 'cauchy'
    seed_kernel_scale: float = 2.3849
    seed_chunk_s: float = 20.0
    seed_growth: float = 0.1
    solver_method: str = 'levenberg_marquardt'
    max_solver_iterations: int = 50
    solver_tolerance: float = 1e-6
    estimate_noise_scale: bool = True
    max_noise_scale: float = 10.0
    model_error_m: float = 0.15
    final_kernel: str = 'cauchy'
    final_kernel_scale: float = 2.3849
    calibrate_odometry: bool = True

    def __post_init__(self) -> None:
        checks: list[tuple[bool, str, object, str]] = [
            (self.mode in MODES, 'mode', self.mode, f'must be one of {MODES}'),
            (
                np.isfinite(self.lagrange_lambda) and self.lagrange_lambda > 0,
                'lagrange_lambda',
                self.lagrange_lambda,
                'must be a finite number > 0',
            ),
            (
                0 < self.moveable_threshold < 1,
                'moveable_threshold',
                self.moveable_threshold,
                'must be in (0, 1)',
            ),
            (self.max_iterations >= 1, 'max_iterations', self.max_iterations, 'must be >= 1'),
            (
                np.isfinite(self.final_kernel_scale) and self.final_kernel_scale > 0,
                'final_kernel_scale',
                self.final_kernel_scale,
                'must be a finite number > 0',
            ),
            (
                self.final_kernel in ('none', *SEED_KERNELS),
                'final_kernel',
                self.final_kernel,
                "must be 'none', 'cauchy' or 'huber'",
            ),
            (
                np.isfinite(self.max_noise_scale) and self.max_noise_scale >= 1,
                'max_noise_scale',
                self.max_noise_scale,
                'must be a finite number >= 1',
            ),
            (
                np.isfinite(self.model_error_m) and self.model_error_m >= 0,
                'model_error_m',
                self.model_error_m,
                'must be a finite number >= 0',
            ),
            (self.weight_tolerance > 0, 'weight_tolerance', self.weight_tolerance, 'must be > 0'),
            (
                0 < self.false_alarm_probability < 1,
                'false_alarm_probability',
                self.false_alarm_probability,
                'must be in (0, 1)',
            ),
            (
                0 < self.gate_probability < 1,
                'gate_probability',
                self.gate_probability,
                'must be in (0, 1)',
            ),
            (
                0 <= self.max_gated_fraction < 1,
                'max_gated_fraction',
                self.max_gated_fraction,
                'must be in [0, 1)',
            ),
            (
                self.seed_kernel in SEED_KERNELS,
                'seed_kernel',
                self.seed_kernel,
                f'must be one of {tuple(SEED_KERNELS)}',
            ),
            (
                self.seed_kernel_scale > 0,
                'seed_kernel_scale',
                self.seed_kernel_scale,
                'must be > 0',
            ),
            (self.seed_chunk_s > 0, 'seed_chunk_s', self.seed_chunk_s, 'must be > 0'),
            (
                np.isfinite(self.seed_growth) and self.seed_growth > 0,
                'seed_growth',
                self.seed_growth,
                'must be a finite number > 0',
            ),
            (
                self.max_solver_iterations >= 1,
                'max_solver_iterations',
                self.max_solver_iterations,
                'must be >= 1',
            ),
        ]
        for ok, name, value, requirement in checks:
            if not ok:
                raise ValueError(f'EM-SAM setting {name}={value!r}: {requirement}')


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
