"""Sparse nonlinear least squares for EM-SAM (Square Root SAM, eq. 4 and 16): Gauss-Newton
and Levenberg-Marquardt with step control; see docs/design/em_sam_core.md."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from em_sam_node.core.factorization import (
    SingularSystemError,
    factorize,
    held_variables,
    hold_uninformed,
)
from em_sam_node.core.factors import observation_residuals, odometry_residuals, prior_residual
from em_sam_node.core.linear_system import (
    SystemLayout,
    checked_row_scale,
    linearize_factors,
    normal_equations,
    system_layout,
)
from em_sam_node.core.problem import Estimate, SlamProblem, SolveResult
from em_sam_node.core.robust_kernels import RobustKernel, kernel_loss, robust_row_scale
from slam_core.arrays import FloatArray
from slam_core.geometry.se2 import wrap_angle

Method = Literal['gauss_newton', 'levenberg_marquardt']

_HYBRID_HALVINGS = 8  # step halvings of the hybrid's Gauss-Newton phase
_MIN_DAMPING = 1e-12  # LM lambda floor, relative to diag(J^T J)
_MIN_DAMPING_DIAGONAL = 1e-6
_MAX_DAMPING_DIAGONAL = 1e32


# --- cost --------------------------------------------------------------------------------


def _cost(
    problem: SlamProblem,
    estimate: Estimate,
    row_scale: FloatArray,
    kernel: RobustKernel | None,
) -> float:
    prior = prior_residual(problem, estimate)
    odometry = odometry_residuals(problem, estimate)
    obs = observation_residuals(problem, estimate)
    squared = np.einsum('ki,ki->k', obs, obs)
    if kernel is None:
        obs_cost = 0.5 * float(np.dot(row_scale * row_scale, squared))
    else:
        loss = kernel_loss(kernel, np.sqrt(squared))
        obs_cost = float(np.dot(row_scale * row_scale, loss))
    return 0.5 * float(prior @ prior) + 0.5 * float(np.vdot(odometry, odometry)) + obs_cost


# --- the solver --------------------------------------------------------------------------


@dataclass(frozen=True)
class _Settings:
    gauss_newton: bool
    max_iterations: int
    relative_cost_tolerance: float
    step_tolerance: float
    gradient_tolerance: float
    initial_damping: float
    max_damping: float
    max_step_halvings: int
    identity_damping: bool = False
    factor_10: bool = False
    expmap: bool = False
    gauss_newton_below: float = 0.0


@dataclass(frozen=True)
class _Trial:
    estimate: Estimate
    cost: float
    fraction: float  # of the computed step that was taken
    gain: float  # actual / predicted cost decrease


def solve(
    problem: SlamProblem,
    initial: Estimate,
    *,
    obs_row_scale: FloatArray | None = None,
    method: Method | str = 'gauss_newton',
    max_iterations: int = 50,
    relative_cost_tolerance: float = 1e-10,
    step_tolerance: float = 1e-9,
    gradient_tolerance: float = 1e-10,
    robust_kernel: RobustKernel | Callable[[FloatArray], FloatArray] | None = None,
    initial_damping: float = 1e-10,
    max_damping: float = 1e12,
    max_step_halvings: int = 8,
    damping: str = 'marquardt',
    damping_update: str = 'nielsen',
    retraction: str = 'additive',
    gauss_newton_below: float = 0.0,
) -> SolveResult:
    """Return the estimate minimizing the (row-scaled, robust) cost, relinearized from initial.

    Raises:
        SingularSystemError: Gauss-Newton on a rank-deficient system.
        ValueError: a setting out of range.
    """
    if not (math.isfinite(gauss_newton_below) and 0.0 <= gauss_newton_below < 1.0):
        raise ValueError(f'gauss_newton_below must be in [0, 1), got {gauss_newton_below!r}')
    if damping not in ('marquardt', 'levenberg'):
        raise ValueError(f"damping must be 'marquardt' or 'levenberg', got {damping!r}")
    if damping_update not in ('nielsen', 'factor_10'):
        raise ValueError(
            f"damping_update must be 'nielsen' or 'factor_10', got {damping_update!r}"
        )
    if retraction not in ('additive', 'expmap'):
        raise ValueError(f"retraction must be 'additive' or 'expmap', got {retraction!r}")
    if method not in ('gauss_newton', 'levenberg_marquardt'):
        raise ValueError(f"method must be 'gauss_newton' or 'levenberg_marquardt', got {method!r}")
    if max_iterations < 0 or max_step_halvings < 0:
        raise ValueError('max_iterations and max_step_halvings must be >= 0')
    if not 0.0 < initial_damping <= max_damping:
        raise ValueError('initial_damping must be > 0 and at most max_damping')
    settings = _Settings(
        gauss_newton=method == 'gauss_newton',
        max_iterations=max_iterations,
        relative_cost_tolerance=relative_cost_tolerance,
        step_tolerance=step_tolerance,
        gradient_tolerance=gradient_tolerance,
        initial_damping=initial_damping,
        max_damping=max_damping,
        max_step_halvings=max_step_halvings,
        identity_damping=damping == 'levenberg',
        factor_10=damping_update == 'factor_10',
        expmap=retraction == 'expmap',
        gauss_newton_below=gauss_newton_below,
    )
    layout = system_layout(problem)
    base_scale = checked_row_scale(problem, obs_row_scale)
    return _Optimizer(problem, layout, base_scale, robust_kernel, settings).run(initial)


class _Optimizer:
    """One solve: the iterate, the cost history, the damping, counters and timers."""

    def __init__(
        self,
        problem: SlamProblem,
        layout: SystemLayout,
        base_scale: FloatArray,
        kernel: RobustKernel | None,
        settings: _Settings,
    ) -> None:
        self.problem = problem
        self.layout = layout
        self.base_scale = base_scale
        self.kernel = kernel
        self.settings = settings
        self.damping = 0.0 if settings.gauss_newton else settings.initial_damping
        self.nu = 2.0
        self.hybrid_damping: float | None = None  # LM's damping while in the GN phase
        self.hybrid_left = False  # the GN phase ended; the hybrid does not switch twice
        self.hybrid_switch = -1  # accepted steps before the GN phase began (-1: never)
        self.iterations = self.rejected = self.halvings = 0
        self.linearize_time_s = self.factorize_time_s = 0.0
        self.history: list[float] = []
        self.estimate = Estimate(np.zeros((0, 3)), np.zeros((0, 2)))
        self.linearization: tuple[FloatArray, FloatArray] | None = None

    def run(self, initial: Estimate) -> SolveResult:
        """Return the SolveResult of relinearizing from initial until a stopping rule holds."""
        started = time.perf_counter()
        held = held_variables(
            self.problem, self.layout, self.base_scale, check_rank=self.settings.gauss_newton
        )
        self.estimate = _initial_copy(self.problem, initial)
        self.history = [self.cost(self.estimate)]
        outcome: tuple[str, bool] | None = None
        while outcome is None and self.iterations < self.settings.max_iterations:
            if self.linearization is None:
                self.linearization = self.linearize()
                gradient = self.linearization[1]
                if np.max(np.abs(gradient), initial=0.0) <= self.settings.gradient_tolerance:
                    outcome = ('gradient_tolerance', True)
                    break
            outcome = self.iterate()
        status, converged = outcome or ('max_iterations', False)
        return SolveResult(
            estimate=self.estimate,
            cost_history=tuple(self.history),
            iterations=self.iterations,
            converged=converged,
            status=status,
            extra={
                'accepted_steps': float(len(self.history) - 1),
                'rejected_steps': float(self.rejected),
                'step_halvings': float(self.halvings),
                'held_variables': float(held.size),
                'final_damping': float(self.damping),
                'gauss_newton_from_step': float(self.hybrid_switch),
                'linearize_time_s': self.linearize_time_s,
                'factorize_time_s': self.factorize_time_s,
                'total_time_s': time.perf_counter() - started,
            },
        )

    def iterate(self) -> tuple[str, bool] | None:
        """Factor, step and backtrack once; return (status, converged) to stop, else None."""
        if self.linearization is None:
            raise RuntimeError('iterate() needs a linearization')
        data, gradient = self.linearization
        settings = self.settings
        self.iterations += 1
        try:
            # The numeric rank test runs on the first Gauss-Newton factorization only: rank
            # deficiency is structural in practice, and the structure was checked before.
            step, curvature = self.step(
                data, gradient, check_rank=settings.gauss_newton and self.iterations == 1
            )
        except SingularSystemError:
            if settings.gauss_newton:
                raise
            if self.hybrid_damping is not None:
                return self.leave_gauss_newton()
            return self.reject()  # LM: an exactly singular damped system needs more damping
        trial = self.backtrack(step, gradient, curvature)
        if trial is None and self.hybrid_damping is not None:
            return self.leave_gauss_newton()
        step_norm = math.sqrt(float(step @ step))
        negligible = settings.step_tolerance * (_norm(self.estimate) + settings.step_tolerance)
        if trial is None:
            if step_norm <= negligible:
                self.rejected += 1
                return ('step_tolerance', True)
            if settings.gauss_newton:
                self.rejected += 1
                predicted = -float(gradient @ step) - 0.5 * curvature
                if predicted <= settings.relative_cost_tolerance * self.history[-1]:
                    return ('cost_tolerance', True)  # at the optimum up to rounding
                return ('diverged', False)
            return self.reject()
        previous = self.history[-1]
        self.accept(trial)
        if previous - trial.cost <= settings.relative_cost_tolerance * previous:
            return ('cost_tolerance', True)
        if (
            self.hybrid_damping is None
            and not self.hybrid_left
            and not settings.gauss_newton
            and previous - trial.cost < settings.gauss_newton_below * previous
        ):
            self.hybrid_damping, self.damping = self.damping, 0.0
            self.hybrid_switch = len(self.history) - 1
        if trial.fraction * step_norm <= negligible:
            return ('step_tolerance', True)
        return None

    def accept(self, trial: _Trial) -> None:
        """Move to the trial point; LM lowers its damping (Nielsen's rule or by 10)."""
        if not self.settings.gauss_newton and self.hybrid_damping is None:
            if self.settings.factor_10:
                self.damping /= 10.0
            else:
                self.damping *= max(1.0 / 3.0, 1.0 - (2.0 * trial.gain - 1.0) ** 3)
            self.damping = max(self.damping, _MIN_DAMPING)
            self.nu = 2.0
        self.estimate = trial.estimate
        self.history.append(trial.cost)
        self.linearization = None

    def leave_gauss_newton(self) -> tuple[str, bool] | None:
        """A Gauss-Newton step of the hybrid failed: count it, go back to LM's damping."""
        assert self.hybrid_damping is not None
        self.rejected += 1
        self.damping, self.hybrid_damping = self.hybrid_damping, None
        self.hybrid_left = True
        return None

    def reject(self) -> tuple[str, bool] | None:
        """Count a rejected LM step and raise the damping (Nielsen: times nu, nu doubles)."""
        self.rejected += 1
        if self.settings.factor_10:
            self.damping *= 10.0
        else:
            self.damping *= self.nu
            self.nu *= 2.0
        if self.damping > self.settings.max_damping:
            return ('damping_limit', False)
        return None

    def cost(self, estimate: Estimate) -> float:
        """Return the cost at the estimate: prior, odometry and row-scaled (robust) sightings."""
        return _cost(self.problem, estimate, self.base_scale, self.kernel)

    def linearize(self) -> tuple[FloatArray, FloatArray]:
        """Return J^T J data (nnz,) and J^T r (n,) at the iterate, robust weights refreshed."""
        started = time.perf_counter()
        scale = robust_row_scale(self.problem, self.estimate, self.base_scale, self.kernel)
        data, gradient = normal_equations(
            self.layout, linearize_factors(self.problem, self.estimate, scale)
        )
        hold_uninformed(self.layout, data)
        self.linearize_time_s += time.perf_counter() - started
        return data, gradient

    def step(
        self, data: FloatArray, gradient: FloatArray, *, check_rank: bool
    ) -> tuple[FloatArray, float]:
        """Return dx (n,) solving (A + damping D) dx = -g, and dx^T A dx."""
        started = time.perf_counter()
        damping_diagonal = np.zeros(0)
        if self.damping > 0.0:
            data = data.copy()
            slots = self.layout.diagonal_slots
            if self.settings.identity_damping:
                damping_diagonal = np.full(slots.shape, self.damping)
            else:
                damping_diagonal = self.damping * np.clip(
                    data[slots], _MIN_DAMPING_DIAGONAL, _MAX_DAMPING_DIAGONAL
                )
            data[slots] += damping_diagonal
        try:
            step = -factorize(self.layout, data, check_rank=check_rank).solve(gradient)
        finally:
            self.factorize_time_s += time.perf_counter() - started
        if not np.all(np.isfinite(step)):
            raise SingularSystemError('the linear solve produced a non-finite step')
        # (A + lambda D) dx = -g  =>  dx^T A dx = -g^T dx - dx^T (lambda D) dx.
        curvature = -float(gradient @ step)
        if self.damping > 0.0:
            curvature -= float(step @ (damping_diagonal * step))
        return step, curvature

    def backtrack(self, step: FloatArray, gradient: FloatArray, curvature: float) -> _Trial | None:
        """Return the first of dx, dx/2, ... that lowers the cost, with its gain ratio, or None."""
        slope = float(gradient @ step)
        cost = self.history[-1]
        fraction = 1.0
        halvings = _HYBRID_HALVINGS if self.hybrid_damping is not None else None
        max_halvings = self.settings.max_step_halvings if halvings is None else halvings
        for halving in range(max_halvings + 1):
            estimate = _retract(
                self.estimate, fraction * step, self.problem.num_poses, self.settings.expmap
            )
            trial_cost = self.cost(estimate)
            if trial_cost < cost:
                self.halvings += halving
                predicted = -fraction * slope - 0.5 * fraction * fraction * curvature
                gain = (cost - trial_cost) / predicted if predicted > 0.0 else 0.0
                return _Trial(estimate, trial_cost, fraction, gain)
            fraction *= 0.5
        self.halvings += max_halvings
        return None


def _retract(estimate: Estimate, step: FloatArray, num_poses: int, expmap: bool) -> Estimate:
    delta = step[: 3 * num_poses].reshape(-1, 3)
    if expmap:
        poses = estimate.poses.copy()
        poses[:, :2] += _arc(estimate.poses[:, 2], delta)
        poses[:, 2] += delta[:, 2]
    else:
        poses = estimate.poses + delta
    poses[:, 2] = wrap_angle(poses[:, 2])
    landmarks = estimate.landmarks + step[3 * num_poses :].reshape(-1, 2)
    return Estimate(poses, landmarks)


def _arc(headings: FloatArray, delta: FloatArray) -> FloatArray:
    """Return the SE(2) exponential's translation (N, 2) for a step (N, 3), map coordinates."""
    w = delta[:, 2]
    small = np.abs(w) < 1e-6
    safe = np.where(small, 1.0, w)
    a = np.where(small, 1.0 - w * w / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 * w, (1.0 - np.cos(safe)) / safe)
    cos, sin = np.cos(headings), np.sin(headings)
    body_x = cos * delta[:, 0] + sin * delta[:, 1]
    body_y = -sin * delta[:, 0] + cos * delta[:, 1]
    arc_x, arc_y = a * body_x - b * body_y, b * body_x + a * body_y
    return np.column_stack([cos * arc_x - sin * arc_y, sin * arc_x + cos * arc_y])


def _norm(estimate: Estimate) -> float:
    return math.sqrt(
        float(np.vdot(estimate.poses, estimate.poses))
        + float(np.vdot(estimate.landmarks, estimate.landmarks))
    )


def _initial_copy(problem: SlamProblem, initial: Estimate) -> Estimate:
    """Return a float64 copy of the initial estimate with wrapped angles, after checks."""
    poses = np.array(initial.poses, dtype=np.float64)
    landmarks = np.array(initial.landmarks, dtype=np.float64)
    poses_shape, landmarks_shape = (problem.num_poses, 3), (problem.num_landmarks, 2)
    if poses.shape != poses_shape or landmarks.shape != landmarks_shape:
        raise ValueError(
            f'the initial estimate has poses {poses.shape} and landmarks {landmarks.shape}; '
            f'the problem needs {poses_shape} and {landmarks_shape}'
        )
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(landmarks))):
        raise ValueError('the initial estimate contains NaN or infinite values')
    poses[:, 2] = wrap_angle(poses[:, 2])
    return Estimate(poses, landmarks)
