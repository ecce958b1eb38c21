"""monoslam_evaluate's figures (PNG): top views of one seed, ATE and pose NEES over time."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.files import write_atomically
from slam_evaluation.monoslam_metrics import POSE_DOF
from slam_evaluation.monoslam_pipeline import (
    VARIANT_TITLES,
)
from slam_evaluation.monoslam_runs import Collected
from slam_evaluation.plotting import render_png


def write_figures(directory: Path, content: Mapping[str, Any], collected: Collected) -> list[Path]:
    """Draw the top views, ATE over time and NEES over time; return the PNG paths."""
    import matplotlib

    matplotlib.use('Agg')
    variants = list(content['variants'])
    if not variants:
        return []
    width = 5.0 * len(variants)
    drawings: list[tuple[str, Callable[[Any, Any], None], Any, tuple[float, float]]] = [
        ('monoslam_ate_time.png', _ate_over_time, (content['curves'], collected), (width, 3.6)),
        ('monoslam_nees.png', _nees_over_time, content['curves'], (width, 3.6)),
    ]
    if collected.topview:  # the simulator's scene only (a sequence has no point truth)
        top = ('monoslam_fig5_topview.png', _topviews, collected.topview, (width, 5.0))
        drawings.insert(0, top)
    return [
        write_atomically(directory / name, render_png(draw, data, size))
        for name, draw, data, size in drawings
    ]


def _topviews(figure: Any, views: Mapping[str, Mapping[str, Any]]) -> None:
    grid = np.atleast_1d(figure.subplots(1, len(views), squeeze=False)).ravel()
    for axes, (variant, data) in zip(grid, views.items(), strict=True):
        static, paths = data['static_truth'], data['object_paths']
        axes.scatter(static[:, 0], static[:, 1], s=6, c='lightgrey', label='static truth')
        for index in range(paths.shape[1]):
            axes.plot(paths[:, index, 0], paths[:, index, 1], '-', color='mistyrose', lw=0.6)
        axes.plot(data['true_path'][:, 0], data['true_path'][:, 1], 'k-', lw=1.0, label='camera')
        axes.plot(
            data['estimate'][:, 0],
            data['estimate'][:, 1],
            '-',
            color='tab:blue',
            lw=0.8,
            label='estimate',
        )
        found, moving = data['map'], data['map_moving']
        axes.scatter(
            found[~moving, 0],
            found[~moving, 1],
            s=10,
            c='tab:blue',
            marker='o',
            label=f'map, static ({(~moving).sum()})',
        )
        axes.scatter(
            found[moving, 0],
            found[moving, 1],
            s=40,
            c='tab:red',
            marker='^',
            edgecolors='k',
            linewidths=0.5,
            label=f'map, moving ({moving.sum()})',
        )
        axes.plot(
            data['target'][:, 0],
            data['target'][:, 1],
            's',
            color='tab:orange',
            ms=4,
            label='target',
        )
        room = data['room']
        axes.set_xlim(-0.5, room[0] + 0.5)
        axes.set_ylim(-0.5, room[1] + 0.5)
        axes.set_aspect('equal')
        axes.set_xlabel('x [m]')
        axes.set_ylabel('y [m]')
        axes.set_title(f'({variant}) {VARIANT_TITLES[variant]}, seed {data["seed"]}', fontsize=9)
        axes.grid(True, lw=0.3)
        axes.legend(fontsize=6, loc='lower right')


def _ate_over_time(figure: Any, data: tuple[Mapping[str, Any], Collected]) -> None:
    curves, collected = data
    grid = np.atleast_1d(
        figure.subplots(1, len(collected.position_error), sharey=True, squeeze=False)
    ).ravel()
    for axes, (variant, errors) in zip(grid, collected.position_error.items(), strict=True):
        times = np.arange(len(errors[0])) / curves['rate_hz']
        for error in errors:
            axes.plot(times, error, '-', color='tab:grey', lw=0.4, alpha=0.6)
        axes.plot(
            times,
            curves[variant]['ate_rms_m'],
            '-',
            color='tab:blue',
            lw=1.2,
            label='RMS over seeds',
        )
        axes.set_yscale('log')
        axes.set_xlabel('time [s]')
        axes.set_title(f'({variant}) camera position error', fontsize=9)
        axes.grid(True, lw=0.3)
    grid[0].set_ylabel('|centre error| [m] (grey: seeds)')
    grid[0].legend(fontsize=7)


def _nees_over_time(figure: Any, curves: Mapping[str, Any]) -> None:
    variants = [k for k in curves if k != 'rate_hz']
    grid = np.atleast_1d(figure.subplots(1, len(variants), sharey=True, squeeze=False)).ravel()
    for axes, variant in zip(grid, variants, strict=True):
        curve = curves[variant]
        times = np.arange(len(curve['nees_mean'])) / curves['rate_hz']
        axes.fill_between(
            times,
            curve['nees_low'],
            curve['nees_high'],
            color='tab:red',
            alpha=0.25,
            step='mid',
            label='95 % band',
        )
        axes.plot(times, curve['nees_mean'], '-', color='tab:blue', lw=0.8, label='average NEES')
        axes.axhline(POSE_DOF, color='k', ls='--', lw=0.8)
        axes.set_yscale('log')
        axes.set_xlabel('time [s]')
        axes.set_title(f'({variant}) pose NEES (6 dof), average over seeds', fontsize=9)
        axes.grid(True, lw=0.3)
    grid[0].legend(fontsize=7)
