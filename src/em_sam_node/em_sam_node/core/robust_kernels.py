"""Robust kernels for the observation factors: IRLS weights w(d) and losses rho(d); see
docs/design/em_sam_core.md."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from em_sam_node.core.factors import observation_residuals
from em_sam_node.core.problem import Estimate, SlamProblem
from slam_core.arrays import FloatArray


class RobustKernel(Protocol):
    """Maps Mahalanobis distances d (K,) to IRLS weights (K,) in [0, 1]; ``loss`` optional."""

    def __call__(self, distance: FloatArray, /) -> FloatArray: ...


@dataclass(frozen=True)
class HuberKernel:
    """Huber: w = 1 for d <= k, k / d beyond; rho = d^2/2, or k d - k^2/2 beyond."""

    threshold: float

    def __call__(self, distance: FloatArray) -> FloatArray:
        """Return the IRLS weights (K,) in (0, 1] for distances d (K,)."""
        d = np.abs(distance)
        return np.where(d <= self.threshold, 1.0, self.threshold / np.maximum(d, 1e-300))

    def loss(self, distance: FloatArray) -> FloatArray:
        """Return rho(d) (K,), the Huber loss."""
        d = np.abs(distance)
        k = self.threshold
        return np.where(d <= k, 0.5 * d * d, k * d - 0.5 * k * k)


@dataclass(frozen=True)
class CauchyKernel:
    """Cauchy: w = 1 / (1 + (d/k)^2); rho = k^2/2 log(1 + (d/k)^2)."""

    scale: float

    def __call__(self, distance: FloatArray) -> FloatArray:
        """Return the IRLS weights (K,) in (0, 1] for distances d (K,)."""
        ratio = np.asarray(distance) / self.scale
        return 1.0 / (1.0 + ratio * ratio)

    def loss(self, distance: FloatArray) -> FloatArray:
        """Return rho(d) (K,), the Cauchy loss."""
        ratio = np.asarray(distance) / self.scale
        return 0.5 * self.scale**2 * np.log1p(ratio * ratio)


def huber_weights(threshold: float = 1.345) -> HuberKernel:
    """Return the Huber kernel d -> w (K,) with the given threshold (Mahalanobis units)."""
    if not threshold > 0.0:
        raise ValueError(f'huber_weights: threshold must be > 0, got {threshold}')
    return HuberKernel(float(threshold))


def cauchy_weights(scale: float = 2.3849) -> CauchyKernel:
    """Return the Cauchy kernel d -> w (K,) with the given scale (Mahalanobis units)."""
    if not scale > 0.0:
        raise ValueError(f'cauchy_weights: scale must be > 0, got {scale}')
    return CauchyKernel(float(scale))


_GAUSS_NODES, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(16)
_GAUSS_NODES = 0.5 * (_GAUSS_NODES + 1.0)  # on [0, 1]
_GAUSS_WEIGHTS = 0.5 * _GAUSS_WEIGHTS


def kernel_loss(kernel: RobustKernel, distance: FloatArray) -> FloatArray:
    """Return rho(d) (K,): kernel.loss(d) if it has one, else the integral of w(t) t, 0 to d."""
    loss = getattr(kernel, 'loss', None)
    if loss is not None:
        return np.asarray(loss(distance), dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    points = d[:, None] * _GAUSS_NODES[None, :]  # rho(d) = d^2 int_0^1 w(s d) s ds
    weights = _checked_weights(kernel, points.ravel()).reshape(points.shape)
    integral: FloatArray = (weights * _GAUSS_NODES) @ _GAUSS_WEIGHTS
    return d * d * integral


def _checked_weights(kernel: RobustKernel, distance: FloatArray) -> FloatArray:
    weights = np.asarray(kernel(distance), dtype=np.float64)
    if weights.shape != distance.shape:
        raise ValueError(
            f'robust_kernel returned weights of shape {weights.shape} for distances of '
            f'shape {distance.shape}; it must return one weight per distance'
        )
    if not np.all((weights >= 0.0) & (weights <= 1.0)):
        raise ValueError('robust_kernel returned weights outside [0, 1] (or NaN)')
    return weights


def robust_row_scale(
    problem: SlamProblem,
    estimate: Estimate,
    row_scale: FloatArray,
    kernel: RobustKernel | None,
) -> FloatArray:
    """Return the observation row scales (K,) times sqrt(w_k), the kernel's IRLS weights at
    the estimate (``row_scale`` itself without a kernel)."""
    if kernel is None:
        return row_scale
    obs = observation_residuals(problem, estimate)
    weights = _checked_weights(kernel, np.sqrt(np.einsum('ki,ki->k', obs, obs)))
    return row_scale * np.sqrt(weights)
