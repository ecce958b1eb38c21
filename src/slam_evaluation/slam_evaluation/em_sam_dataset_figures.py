"""Figures of em_sam_evaluate on real data sets: an MRCLAM run's static map against the
Vicon landmarks, and the Victoria Park trees EM-SAM flagged, with their sightings."""

from __future__ import annotations

from typing import Any

import numpy as np

from slam_evaluation.em_sam_mrclam import MAP_OUTLIER_M, MrclamRunResult
from slam_evaluation.em_sam_victoria_park import VictoriaParkResult

ZOOM_PANELS = 6  # flagged Victoria Park trees shown close up, the worst first
MRCLAM_SIZE_IN = (12.0, 5.5)
VICTORIA_PARK_SIZE_IN = (14.0, 7.0)


def draw_mrclam_run(figure: Any, result: MrclamRunResult) -> None:
    """Left: EM-SAM robust's static map and trajectory, aligned onto the Vicon landmarks
    (landmarks further off than MAP_OUTLIER_M named in red), and the sightings of the
    robots it flagged. Right: every landmark's weight."""
    robust, truth, error = result.robust, result.truth, result.robust_map
    ax_map, ax_weights = figure.subplots(1, 2, width_ratios=(1.4, 1.0))

    def aligned(points: np.ndarray) -> np.ndarray:
        return error.alignment.apply(points) if error is not None else points

    static_truth = ~truth.moveable & np.all(np.isfinite(truth.positions_before), axis=1)
    ax_map.plot(*aligned(robust.poses[:, :2]).T, color='0.75', lw=0.6, label='EM-SAM robust')
    ax_map.plot(*truth.positions_before[static_truth].T, 'ks', mfc='none', ms=7, label='Vicon')
    kept = ~robust.moveable
    ax_map.plot(*aligned(robust.positions[kept]).T, 'g.', ms=8, label='static estimate')
    for subject, sightings in robust.sightings.items():
        ax_map.plot(*aligned(sightings.positions).T, '.', ms=2, label=f'{subject} sightings')
    if error is not None:
        far = set(error.far_ids)
        placed = aligned(robust.positions[kept])
        for lid, position in zip(robust.landmark_ids[kept], placed, strict=True):
            if int(lid) in far:
                ax_map.annotate(str(int(lid)), position, color='red', fontsize=8)
    title = f'{result.name}: static map aligned on landmarks within {MAP_OUTLIER_M} m'
    ax_map.set_title(title if error is not None else f'{result.name} (not aligned)', fontsize=9)
    ax_map.set_aspect('equal')
    ax_map.legend(fontsize=6, loc='best')
    ids = robust.landmark_ids
    ax_weights.bar(range(len(ids)), robust.weights, color=np.where(robust.moveable, 'C3', 'C2'))
    ax_weights.set_xticks(range(len(ids)), [str(i) for i in ids.tolist()], fontsize=7)
    ax_weights.set_xlabel('subject (1-5 robots, 6-20 barcodes)')
    ax_weights.set_ylabel('EM weight (robust)')
    ax_weights.set_ylim(0.0, 1.05)


def draw_victoria_park(figure: Any, result: VictoriaParkResult) -> None:
    """Left: the all-static trajectory and trees, the flagged trees' sightings placed
    through it and their all-static positions. Right: the worst flagged trees close up."""
    static = result.all_static
    grid = figure.add_gridspec(2, 1 + (ZOOM_PANELS + 1) // 2, width_ratios=(3, *[1] * 3))
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
    overview.set_aspect('equal')
    overview.legend(fontsize=7, loc='best')
    for panel, tree in enumerate(result.flagged[:ZOOM_PANELS]):
        ax = figure.add_subplot(grid[panel % 2, 1 + panel // 2])
        ax.plot(*tree.sightings_m.T, '.', color='C3', ms=4)
        ax.plot(*tree.fitted_m, 'kx', ms=8)
        ax.set_title(
            f'tree {tree.tree}: {len(tree.sightings_m)} sightings, w {tree.weight:.2f}\n'
            f'max {tree.max_distance_m:.1f} m from the x',
            fontsize=8,
        )
        ax.set_aspect('equal', adjustable='datalim')
        ax.tick_params(labelsize=6)
