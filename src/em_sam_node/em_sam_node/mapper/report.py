"""EM-SAM reports: a JSON summary and PNG figures (the paper's Figs. 2-5, weights per
iteration), each written atomically; see docs/design/em_sam_core.md."""

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


MAX_ID_LABELS = 80
"""Landmark ids are written next to the landmarks up to this many (beyond, they would hide
the map; the weights figure names every id)."""


def draw_map(
    axes: Any,
    poses: np.ndarray,
    ids: np.ndarray,
    positions: np.ndarray,
    moveable: np.ndarray | None,
    sightings: Mapping[int, Any] | None,
    title: str,
) -> None:
    """Draw poses (red), static landmarks (green), moveable ones (blue, sightings dotted)."""
    axes.plot(poses[:, 0], poses[:, 1], '-', color='tab:red', lw=0.8, label='trajectory')
    flags = np.zeros(len(ids), dtype=bool) if moveable is None else moveable
    static = ~flags
    axes.scatter(
        positions[static, 0],
        positions[static, 1],
        c='tab:green',
        s=18,
        label='static landmark',
        zorder=3,
    )
    for index in np.flatnonzero(flags):
        history = (sightings or {}).get(int(ids[index]))
        if history is not None:
            points = history.positions[::-1]
            axes.plot(points[:, 0], points[:, 1], ':', color='tab:blue', lw=1.0)
            axes.scatter(points[:, 0], points[:, 1], c='tab:blue', s=8, zorder=3)
        axes.scatter(*positions[index], c='tab:blue', marker='s', s=24, zorder=4)
    if flags.any():
        axes.plot([], [], ':o', color='tab:blue', ms=3, lw=1.0, label='moveable: its sightings')
        axes.scatter([], [], c='tab:blue', marker='s', s=24, label='moveable: latest sighting')
    if len(ids) <= MAX_ID_LABELS:
        for row, landmark_id in enumerate(ids.tolist()):
            axes.annotate(
                str(landmark_id),
                positions[row],
                xytext=(3, 3),
                textcoords='offset points',
                fontsize=6,
                color='tab:blue' if flags[row] else 'darkgreen',
            )
    axes.set_title(title)
    axes.set_aspect('equal', adjustable='box')
    axes.set_xlabel('x [m]')
    axes.set_ylabel('y [m]')
    axes.grid(True, lw=0.3)


def map_figure_size(
    poses: np.ndarray, positions: np.ndarray, width_in: float = 7.0
) -> tuple[float, float]:
    """A figure size whose map area has the data's aspect (within 1:3 and 3:1)."""
    points = np.vstack([poses[:, :2], positions.reshape(-1, 2)])
    points = points[np.all(np.isfinite(points), axis=1)]
    span = np.ptp(points, axis=0) if len(points) else np.ones(2)
    aspect = float(np.clip((span[1] + 1.0) / (span[0] + 1.0), 1 / 3, 3))
    return (width_in + 2.5, min(max(width_in * aspect, 3.0), 12.0))


def draw_weights(axes: Any, result: EmResult) -> Any:
    """Every landmark's weight per EM iteration as a table of colours; return the image."""
    history = result.weight_history
    order = np.lexsort((result.landmark_ids, ~result.moveable))
    image = axes.imshow(
        history[:, order].T,
        aspect='auto',
        cmap='RdYlGn',
        vmin=0.0,
        vmax=1.0,
        interpolation='nearest',
    )
    axes.set_xticks(np.arange(history.shape[0]))
    axes.set_xlabel('EM iteration (0: before the first M-step)')
    labels = [str(i) for i in result.landmark_ids[order].tolist()]
    axes.set_yticks(
        np.arange(len(labels)), labels, fontsize=max(4, min(8, 400 // max(len(labels), 1)))
    )
    for tick, index in zip(axes.get_yticklabels(), order.tolist(), strict=True):
        tick.set_color('tab:blue' if result.moveable[index] else 'black')
    axes.set_ylabel('landmark id (blue: moveable)')
    axes.set_title(
        f'EM weight w_l per iteration: {int(result.moveable.sum())} of '
        f'{len(result.landmark_ids)} landmarks moveable (w_l < 0.5)'
    )
    return image


def write_figures(result: EmResult, directory: Path, *, prefix: str = 'em_sam') -> list[Path]:
    """Write the map, stage snapshots and weights-per-iteration PNGs; return their paths."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    written = []
    size = map_figure_size(result.poses, result.positions)
    figure, axes = plt.subplots(figsize=size, layout='constrained')
    draw_map(
        axes,
        result.poses,
        result.landmark_ids,
        result.positions,
        result.moveable,
        result.sightings,
        f'EM-SAM ({result.mode}): final map, {int(result.moveable.sum())} moveable landmarks',
    )
    axes.legend(loc='upper left', bbox_to_anchor=(1.02, 1.0), fontsize=8)
    written.append(write_atomically(directory / f'{prefix}_map.png', _figure_bytes(figure)))
    plt.close(figure)

    if result.snapshots:
        stages = [s for s in SNAPSHOT_TITLES if s in result.snapshots]
        figure, grid = plt.subplots(
            1, len(stages), figsize=(4.2 * len(stages), size[1]), layout='constrained'
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
        np.atleast_1d(grid)[-1].legend(loc='upper left', bbox_to_anchor=(1.02, 1.0), fontsize=7)
        written.append(write_atomically(directory / f'{prefix}_stages.png', _figure_bytes(figure)))
        plt.close(figure)

    rows = len(result.landmark_ids)
    figure, axes = plt.subplots(figsize=(7, min(3.0 + 0.12 * rows, 20.0)), layout='constrained')
    image = draw_weights(axes, result)
    figure.colorbar(image, ax=axes, label='weight w_l (0: moveable, 1: static)')
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
