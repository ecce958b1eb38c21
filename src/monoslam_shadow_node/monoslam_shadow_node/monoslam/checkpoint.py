"""monoslam's checkpoint: the processor's map and tracking state in one versioned .npz file.

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from monoslam_shadow_node.monoslam.conversions import PoseFields
from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
from monoslam_shadow_node.monoslam.core.monoslam_snapshot import (
    filter_state,
    restore_filter,
    saved_camera,
)
from monoslam_shadow_node.monoslam.core.monoslam_types import UpdateCounts
from monoslam_shadow_node.monoslam.processor import MonoSlamCounts, MonoSlamProcessor
from slam_core.checkpoint import CheckpointError, load_checkpoint_arrays, save_arrays, shaped

FORMAT = 'monoslam checkpoint'
VERSION = 1
__all__ = ['CheckpointError', 'load_checkpoint', 'save_checkpoint']


def _trajectory_arrays(trajectory: Sequence[PoseFields]) -> dict[str, np.ndarray]:
    return {
        'trajectory_stamp_ns': np.array([p.stamp_ns for p in trajectory], dtype=np.int64),
        'trajectory_position': np.array([p.position for p in trajectory]).reshape(-1, 3),
        'trajectory_orientation': np.array([p.orientation for p in trajectory]).reshape(-1, 4),
        'trajectory_covariance': np.array([p.covariance for p in trajectory]).reshape(-1, 36),
    }


def save_checkpoint(
    processor: MonoSlamProcessor, path: Path, trajectory: Sequence[PoseFields] = ()
) -> None:
    """Write the processor's state and ``trajectory`` atomically; ValueError before the camera."""
    if processor.slam is None:
        raise ValueError('no map yet: no camera_info has come')
    arrays, filter_meta = filter_state(processor.slam)
    counts = dataclasses.asdict(processor.counts)
    meta = {
        'format': FORMAT,
        'version': VERSION,
        'last_ns': processor.sync.last_ns,
        'counts': counts,
        'filter': filter_meta,
    }
    save_arrays(path, {**arrays, **_trajectory_arrays(trajectory)}, meta)


def _counts(values: dict[str, Any]) -> MonoSlamCounts:
    fields = {f.name for f in dataclasses.fields(MonoSlamCounts)}
    if set(values) != fields:
        raise ValueError(f'counts {sorted(set(values) ^ fields)} missing or unknown')
    update = UpdateCounts(**{k: int(v) for k, v in values['update'].items()})
    dropped = {str(k): int(v) for k, v in values['dropped'].items()}
    plain = {k: int(v) for k, v in values.items() if k not in ('update', 'dropped')}
    return MonoSlamCounts(**plain, dropped=dropped, update=update)


def _trajectory(arrays: dict[str, np.ndarray]) -> list[PoseFields]:
    stamps = shaped(arrays, 'trajectory_stamp_ns', (None,))
    count = len(stamps)
    position = shaped(arrays, 'trajectory_position', (count, 3))
    orientation = shaped(arrays, 'trajectory_orientation', (count, 4))
    covariance = shaped(arrays, 'trajectory_covariance', (count, 36))
    return [
        PoseFields(
            int(stamps[k]),
            tuple(map(float, position[k])),  # type: ignore[arg-type]
            tuple(map(float, orientation[k])),  # type: ignore[arg-type]
            tuple(map(float, covariance[k])),
        )
        for k in range(count)
    ]


def _restore(
    processor: MonoSlamProcessor, arrays: dict[str, np.ndarray], meta: dict[str, Any]
) -> list[PoseFields]:
    filter_meta = meta['filter']
    slam = MonoSlam(saved_camera(arrays, filter_meta), processor.config)
    restore_filter(slam, arrays, filter_meta)
    counts = _counts(meta['counts'])
    trajectory = _trajectory(arrays)
    last_ns = meta['last_ns']
    processor.resume(slam, counts, None if last_ns is None else int(last_ns))
    return trajectory


def load_checkpoint(processor: MonoSlamProcessor, path: Path) -> list[PoseFields]:
    """Restore the processor from ``path``; return its trajectory. Raises CheckpointError."""
    return load_checkpoint_arrays(
        path, FORMAT, VERSION, 'monoslam', lambda arrays, meta: _restore(processor, arrays, meta)
    )
