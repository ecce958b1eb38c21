"""Figures of the evaluators: one matplotlib figure drawn into PNG bytes."""

from __future__ import annotations

import io
from collections.abc import Callable
from typing import Any


def render_png(draw: Callable[[Any, Any], None], data: Any, size: tuple[float, float]) -> bytes:
    """Return the PNG bytes of a figure of ``size`` (inches) that ``draw(figure, data)`` fills."""
    import matplotlib.pyplot as plt

    figure = plt.figure(figsize=size, layout='constrained')
    try:
        draw(figure, data)
        buffer = io.BytesIO()
        figure.savefig(buffer, format='png', dpi=110)
        return buffer.getvalue()
    finally:
        plt.close(figure)
