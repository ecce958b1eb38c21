"""Figures of em_sam_evaluate on real data sets (MRCLAM map, Victoria Park flags)."""

from __future__ import annotations

from typing import Any

import numpy as np

from slam_evaluation.em_sam_mrclam import MAP_OUTLIER_M, MrclamRunResult
from slam_evaluation.em_sam_victoria_park import VictoriaParkResult
from slam_sim.core.mrclam import ROBOT_SUBJECTS

ZOOM_PANELS = 6  # flagged Victoria Park trees shown close up, the worst first
MRCLAM_SIZE_IN = (12.0, 7.0)


def draw_mrclam_run(figure: Any, result: MrclamRunResult) -> None:
    """Left: EM-SAM robust's static map, trajectory and flagged robots' sightings on the
    Vicon landmarks (further off than MAP_OUTLIER_M red). Right: every landmark's weight."""
    robust, truth, error = result.robust, result.truth, result.robust_map
    ax_map, ax_weights = figure.subplots(1, 2, width_ratios=(1.2, 1.0))

    def aligned(points: np.ndarray) -> np.ndarray:
        return error.alignment.apply(points) if error is not None else points

    static_truth = ~truth.moveable & np.all(np.isfinite(truth.positions_before), axis=1)
    ax_map.plot(*aligned(robust.poses[:, :2]).T, color='0.75', lw=0.6, label='EM-SAM robust')
    ax_map.plot(*truth.positions_before[static_truth].T, 'ks', mfc='none', ms=7, label='Vicon')
    kept = ~robust.moveable
    ax_map.plot(*aligned(robust.positions[kept]).T, 'g.', ms=8, label='static estimate')
    for subject, sightings in robust.sightings.items():
        name = f'robot {subject}' if subject in ROBOT_SUBJECTS else f'barcode {subject}'
        ax_map.plot(*aligned(sightings.positions).T, '.', ms=2, label=f"{name}'s sightings")
    far = set(error.far_ids) if error is not None else set()
    placed = aligned(robust.positions[kept])
    for lid, position in zip(robust.landmark_ids[kept], placed, strict=True):
        off = int(lid) in far  # more than MAP_OUTLIER_M from Vicon's: in red
        ax_map.annotate(
            str(int(lid)),
            position,
            xytext=(3, 3),
            textcoords='offset points',
            color='red' if off else 'darkgreen',
            fontsize=8 if off else 6,
        )
    title = f'{result.name}: static map aligned on landmarks within {MAP_OUTLIER_M} m'
    ax_map.set_title(title if error is not None else f'{result.name} (not aligned)', fontsize=9)
    ax_map.set_aspect('equal', adjustable='box')
    ax_map.set_xlabel('x [m] (Vicon frame)' if error is not None else 'x [m]')
    ax_map.set_ylabel('y [m]')
    ax_map.legend(fontsize=6, loc='upper left', bbox_to_anchor=(0.0, -0.12), ncols=3)
    ids = robust.landmark_ids
    flags = robust.moveable
    where = np.arange(len(ids))
    ax_weights.vlines(where, 0.0, robust.weights, color='0.7', lw=1.0)
    ax_weights.plot(where[~flags], robust.weights[~flags], 'o', color='C2', label='static')
    ax_weights.plot(where[flags], robust.weights[flags], 's', color='C3', label='moveable')
    ax_weights.axhline(0.5, color='k', ls='--', lw=0.6, label='threshold 0.5')
    ax_weights.set_xticks(where, [str(i) for i in ids.tolist()], fontsize=7)
    ax_weights.set_xlabel('subject (1-5 robots, 6-20 barcodes)')
    ax_weights.set_ylabel('EM weight (robust)')
    ax_weights.set_ylim(-0.05, 1.05)
    ax_weights.legend(fontsize=7, loc='center right')


def draw_victoria_park(figure: Any, result: VictoriaParkResult) -> None:
    """Left: the all-static trajectory and trees, the flagged trees' sightings placed
    through it and their all-static positions. Right: the worst flagged trees close up."""
    static = result.all_static
    zoomed = result.flagged[:ZOOM_PANELS]
    columns = (len(zoomed) + 1) // 2  # as many close-ups as trees flagged: no empty panels
    grid = figure.add_gridspec(2, 1 + columns, width_ratios=(3, *[1] * columns))
    overview = figure.add_subplot(grid[:, 0])
    overview.plot(*static.poses[:, :2].T, color='0.8', lw=0.5, label='all-static trajectory')
    overview.plot(*static.positions.T, 'g.', ms=3, label='trees (all static)')
    for index, tree in enumerate(result.flagged):
        overview.plot(
            *tree.sightings_m.T,
            '.',
            color='C3',
            ms=2,
            label=None if index else 'sightings of flagged trees',
        )
        overview.plot(*tree.fitted_m, 'kx', ms=5)
    overview.set_title(f'Victoria Park: trees EM-SAM robust flagged: {len(result.flagged)}')
    overview.set_aspect('equal', adjustable='box')
    overview.set_xlabel('x [m]')
    overview.set_ylabel('y [m]')
    overview.plot([], [], 'kx', ms=5, label="a flagged tree's all-static position")
    overview.legend(fontsize=7, loc='best')
    for panel, tree in enumerate(zoomed):
        ax = figure.add_subplot(grid[panel % 2, 1 + panel // 2])
        ax.plot(*tree.sightings_m.T, '.', color='C3', ms=4)
        ax.plot(*tree.fitted_m, 'kx', ms=8)
        ax.set_title(
            f'tree {tree.tree}: {len(tree.sightings_m)} sightings, w {tree.weight:.2f}\n'
            f'max {tree.max_distance_m:.1f} m from the x',
            fontsize=8,
        )
        ax.set_aspect('equal', adjustable='datalim')
        ax.set_xlabel('x [m]', fontsize=7)
        ax.set_ylabel('y [m]', fontsize=7)
        ax.tick_params(labelsize=6)


def victoria_park_size_in(result: VictoriaParkResult) -> tuple[float, float]:
    """The Victoria Park figure's size: the overview and as many close-up columns as needed."""
    columns = (min(len(result.flagged), ZOOM_PANELS) + 1) // 2
    return (8.0 + 2.4 * columns, 7.0)
