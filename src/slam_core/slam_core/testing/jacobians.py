"""Finite-difference Jacobians for checking analytic ones (usage: docs/design/ros_and_core.md)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from slam_core.arrays import FloatArray
from slam_core.geometry.se2 import wrap_angle


def numerical_jacobian(
    f: Callable[[FloatArray], ArrayLike],
    x: ArrayLike,
    *,
    eps: float = 1e-6,
    wrap: Sequence[int] | None = None,
    batched: bool = False,
) -> FloatArray:
    """Return the central-difference Jacobian of f at x: (m, n), or (B, m, n) when batched."""
    x0 = np.array(x, dtype=np.float64)
    if eps <= 0.0:
        raise ValueError(f'eps must be positive, got {eps}')
    if batched and x0.ndim != 2:
        raise ValueError(f'batched x must have shape (B, n), got {x0.shape}')
    if not batched and x0.ndim != 1:
        raise ValueError(f'x must have shape (n,) (use batched=True for (B, n)), got {x0.shape}')
    columns = []
    for coordinate in range(x0.shape[-1]):
        plus, minus = x0.copy(), x0.copy()
        plus[..., coordinate] += eps
        minus[..., coordinate] -= eps
        difference = _as_output(f(plus), batched) - _as_output(f(minus), batched)
        if wrap is not None:
            angles = list(wrap)
            difference[..., angles] = wrap_angle(difference[..., angles])
        columns.append(difference / (2.0 * eps))
    return np.stack(columns, axis=-1)


def assert_jacobian_close(
    analytic: ArrayLike,
    f: Callable[[FloatArray], ArrayLike],
    x: ArrayLike,
    *,
    atol: float,
    rtol: float = 1e-5,
    eps: float = 1e-6,
    wrap: Sequence[int] | None = None,
    batched: bool = False,
) -> None:
    """Raise AssertionError naming the worst entry if analytic differs from finite differences."""
    numeric = numerical_jacobian(f, x, eps=eps, wrap=wrap, batched=batched)
    expected = np.asarray(analytic, dtype=np.float64)
    if expected.shape != numeric.shape:
        raise AssertionError(
            f'analytic Jacobian has shape {expected.shape}, finite differences {numeric.shape}'
        )
    excess = np.abs(expected - numeric) - (atol + rtol * np.abs(numeric))
    if expected.size and np.max(excess) > 0.0:
        worst = np.unravel_index(int(np.argmax(excess)), excess.shape)
        bad = int(np.count_nonzero(excess > 0.0))
        raise AssertionError(
            f'{bad} of {expected.size} Jacobian entries differ from central differences; '
            f'worst at index {tuple(int(i) for i in worst)}: analytic {expected[worst]:.9g}, '
            f'numeric {numeric[worst]:.9g} (atol {atol:g}, rtol {rtol:g}, eps {eps:g})'
        )


def _as_output(value: ArrayLike, batched: bool) -> FloatArray:
    out = np.array(value, dtype=np.float64)
    if batched:
        if out.ndim == 1:
            out = out[:, None]  # one scalar output per batch row
        if out.ndim != 2:
            raise ValueError(f'batched f must return (B, m), got {out.shape}')
    else:
        out = out.reshape(-1)
    return out
