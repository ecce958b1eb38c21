"""monoslam_image_evaluate's figures (PNG): trajectory top views, position error over time."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.files import write_atomically
from slam_evaluation.monoslam_image_report import error_curves, rms_over_seeds
from slam_evaluation.monoslam_image_runs import SeedResult
from slam_evaluation.plotting import render_png

RUN_STYLES = {
    'image a': {'color': 'tab:green', 'lw': 0.8},
    'image b': {'color': 'tab:red', 'lw': 0.6, 'alpha': 0.7},
    'image c': {'color': 'tab:blue', 'lw': 1.0},
    'measurement c': {'color': 'tab:orange', 'lw': 1.0, 'ls': '--'},
}
MAP_RUN = 'image c'
"""The run whose map the top views show: the system (the Shadow filter's variant, from
images)."""
TOPVIEW_COLUMNS = 5
TOPVIEW_MARGIN_M = 0.75


def write_figures(directory: Path, results: Sequence[SeedResult], rate_hz: float) -> list[Path]:
    """Draw the top views (one per seed) and the position error; return the PNG paths."""
    import matplotlib

    matplotlib.use('Agg')
    if not results:
        return []
    columns = min(TOPVIEW_COLUMNS, len(results))
    rows = math.ceil(len(results) / columns)
    drawings: list[tuple[str, Callable[[Any, Any], None], Any, tuple[float, float]]] = [
        ('monoslam_image_topview.png', _topviews, results, (4.0 * columns + 2.0, 3.6 * rows)),
        ('monoslam_image_ate_time.png', _errors_over_time, (results, rate_hz), (11.0, 3.8)),
    ]
    return [
        write_atomically(directory / name, render_png(draw, data, size))
        for name, draw, data, size in drawings
    ]


def _topviews(figure: Any, results: Sequence[SeedResult]) -> None:
    columns = min(TOPVIEW_COLUMNS, len(results))
    rows = math.ceil(len(results) / columns)
    grid = np.atleast_1d(figure.subplots(rows, columns, squeeze=False)).ravel()
    for axes, result in zip(grid, results, strict=False):
        truth = result.truth
        points = result.map_points.get(MAP_RUN, np.zeros((0, 3)))
        axes.scatter(
            points[:, 0],
            points[:, 1],
            s=4,
            c='tab:blue',
            alpha=0.35,
            label=f'{MAP_RUN} map points',
        )
        axes.plot(truth[:, 0], truth[:, 1], 'k-', lw=1.6, alpha=0.5, label='true camera path')
        for name, centres in result.centres.items():
            axes.plot(centres[:, 0], centres[:, 1], label=f'{name} camera', **RUN_STYLES[name])
        extent = np.vstack([truth[:, :2], points[:, :2]]) if len(points) else truth[:, :2]
        low = extent.min(axis=0) - TOPVIEW_MARGIN_M
        high = extent.max(axis=0) + TOPVIEW_MARGIN_M
        axes.set_xlim(low[0], high[0])
        axes.set_ylim(low[1], high[1])
        axes.set_aspect('equal')
        axes.set_xlabel('x [m]')
        axes.set_ylabel('y [m]')
        axes.set_title(f'seed {result.entry["seed"]}: camera top view', fontsize=9)
        axes.grid(True, lw=0.3)
    grid[0].legend(fontsize=6, loc='upper left', bbox_to_anchor=(1.02, 1.0))
    for axes in grid[len(results) :]:
        axes.set_visible(False)


def _errors_over_time(figure: Any, data: tuple[Sequence[SeedResult], float]) -> None:
    results, rate_hz = data
    curves = error_curves(results)
    left, right = figure.subplots(1, 2, sharey=True)
    for name, values in curves.items():
        times = np.arange(values.shape[1]) / rate_hz
        left.plot(times, rms_over_seeds(values), label=name, **RUN_STYLES[name])
        if name in ('image c', 'measurement c'):
            for row in values:
                right.plot(times, row, color=RUN_STYLES[name]['color'], lw=0.4, alpha=0.6)
    over = 'RMS over seeds' if len(results) > 1 else f'seed {results[0].entry["seed"]}'
    left.set_title(f'camera position error, {over}', fontsize=9)
    right.set_title('per seed: image c (blue), measurement c (orange)', fontsize=9)
    left.set_ylabel('|centre error| [m]')
    for axes in (left, right):
        axes.set_yscale('log')
        axes.set_xlabel('time [s]')
        axes.grid(True, lw=0.3)
    left.legend(fontsize=7)
