"""EM-SAM reports: a JSON summary and PNG figures, each written atomically.

Figures follow the paper: the map with poses in red, static landmarks in green and moveable
landmarks in blue with their sightings joined by a dotted line (Fig. 5), snapshots of the
estimate at the paper's stages (Figs. 2-5), and the weight of every landmark per EM iteration.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from em_sam_node.core.em_types import EmResult, Snapshot
from slam_core.files import write_atomically, write_json

SNAPSHOT_TITLES = {
    'initial': 'initial (odometry)',
    'all_static': 'all landmarks static (plain SAM)',
    'em_iteration_2': 'after two EM iterations',
    'final': 'final, moveable landmarks removed',
}


def result_summary(result: EmResult, stamps_ns: np.ndarray) -> dict[str, Any]:
    """Return a JSON-ready summary of an EM-SAM result."""
    landmarks = []
    for index, landmark_id in enumerate(result.landmark_ids.tolist()):
        entry: dict[str, Any] = {
            'id': landmark_id,
            'position_m': result.positions[index].tolist(),
            'covariance_m2': result.covariances[index].reshape(4).tolist(),
            'weight': float(result.weights[index]),
            'moveable': bool(result.moveable[index]),
            'num_observations': int(result.num_observations[index]),
        }
        if landmark_id in result.sightings:
            sightings = result.sightings[landmark_id]
            entry['sightings'] = [
                {'stamp_ns': int(s), 'position_m': p.tolist()}
                for s, p in zip(sightings.stamps_ns, sightings.positions, strict=True)
            ]
        landmarks.append(entry)
    return {
        'mode': result.mode,
        'num_keyframes': int(result.poses.shape[0]),
        'num_landmarks': len(landmarks),
        'moveable_ids': result.landmark_ids[result.moveable].tolist(),
        'em_iterations': result.em_iterations,
        'converged': result.converged,
        'num_pieces': result.num_pieces,
        'sighting_variance_factors': {
            'em_test': {
                'range': float(result.noise_scale[0]),
                'bearing': float(result.noise_scale[1]),
            },
            'final_solve': {
                'range': float(result.final_noise_scale[0]),
                'bearing': float(result.final_noise_scale[1]),
            },
        },
        'odometry_calibration': {
            'translation_scale': float(result.odometry_calibration[0]),
            'rotation_scale': float(result.odometry_calibration[1]),
        },
        'timings_s': result.timings_s,
        'weight_history': result.weight_history.tolist(),
        'landmarks': landmarks,
        'trajectory': {
            'stamps_ns': [int(s) for s in stamps_ns],
            'poses': result.poses.tolist(),
        },
    }


def _figure_bytes(figure: Any) -> bytes:
    import io

    buffer = io.BytesIO()
    figure.savefig(buffer, format='png', dpi=110, bbox_inches='tight')
    return buffer.getvalue()


def draw_map(
    axes: Any,
    poses: np.ndarray,
    ids: np.ndarray,
    positions: np.ndarray,
    moveable: np.ndarray | None,
    sightings: Mapping[int, Any] | None,
    title: str,
) -> None:
    """Draw poses (red), static landmarks (green), moveable ones (blue, dotted history)."""
    axes.plot(poses[:, 0], poses[:, 1], '-', color='tab:red', lw=0.8, label='poses')
    flags = np.zeros(len(ids), dtype=bool) if moveable is None else moveable
    static = ~flags
    axes.scatter(
        positions[static, 0], positions[static, 1], c='tab:green', s=18, label='static', zorder=3
    )
    for index in np.flatnonzero(flags):
        history = (sightings or {}).get(int(ids[index]))
        if history is not None:
            points = history.positions[::-1]
            axes.plot(points[:, 0], points[:, 1], ':', color='tab:blue', lw=1.0)
            axes.scatter(points[:, 0], points[:, 1], c='tab:blue', s=8, zorder=3)
        axes.scatter(*positions[index], c='tab:blue', marker='s', s=24, zorder=4)
    if flags.any():
        axes.scatter([], [], c='tab:blue', marker='s', s=24, label='moveable')
    axes.set_title(title)
    axes.set_aspect('equal', adjustable='datalim')
    axes.set_xlabel('x [m]')
    axes.set_ylabel('y [m]')
    axes.grid(True, lw=0.3)


def write_figures(result: EmResult, directory: Path, *, prefix: str = 'em_sam') -> list[Path]:
    """Write the map, stage snapshots and weights-per-iteration PNGs; return their paths."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    written = []
    figure, axes = plt.subplots(figsize=(9, 4.5), layout='constrained')
    draw_map(
        axes,
        result.poses,
        result.landmark_ids,
        result.positions,
        result.moveable,
        result.sightings,
        f'EM-SAM ({result.mode}): final map',
    )
    axes.legend(loc='best', fontsize=8)
    written.append(write_atomically(directory / f'{prefix}_map.png', _figure_bytes(figure)))
    plt.close(figure)

    if result.snapshots:
        stages = [s for s in SNAPSHOT_TITLES if s in result.snapshots]
        figure, grid = plt.subplots(
            1, len(stages), figsize=(4.2 * len(stages), 6), layout='constrained'
        )
        for axes, stage in zip(np.atleast_1d(grid), stages, strict=True):
            snapshot: Snapshot = result.snapshots[stage]
            final = stage == 'final'
            draw_map(
                axes,
                snapshot.poses,
                snapshot.landmark_ids,
                snapshot.landmarks,
                result.moveable if final else None,
                result.sightings if final else None,
                SNAPSHOT_TITLES[stage],
            )
        written.append(write_atomically(directory / f'{prefix}_stages.png', _figure_bytes(figure)))
        plt.close(figure)

    figure, axes = plt.subplots(figsize=(7, 4), layout='constrained')
    history = result.weight_history
    iterations = np.arange(history.shape[0])
    for index in range(len(result.landmark_ids)):
        color = 'tab:blue' if result.moveable[index] else 'tab:green'
        axes.plot(iterations, history[:, index], '-', color=color, lw=0.8, alpha=0.8)
    axes.axhline(0.5, color='k', ls='--', lw=0.6)
    axes.set_xlabel('EM iteration')
    axes.set_ylabel('weight w_l')
    axes.set_ylim(-0.05, 1.05)
    axes.set_title('weights per EM iteration (blue: classified moveable)')
    written.append(write_atomically(directory / f'{prefix}_weights.png', _figure_bytes(figure)))
    plt.close(figure)
    return written


def write_report(
    result: EmResult,
    stamps_ns: np.ndarray,
    directory: Path,
    extra: Mapping[str, Any] | None = None,
) -> list[Path]:
    """Write em_sam_report.json and the figures into ``directory``; return the paths."""
    content = result_summary(result, stamps_ns)
    if extra:
        content.update(extra)
    paths = [write_json(directory / 'em_sam_report.json', content)]
    paths += write_figures(result, directory)
    return paths
