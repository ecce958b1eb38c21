"""em_sam_mapper's checkpoint: the processor's whole state in one versioned .npz file,
saved atomically; see docs/design/em_sam_core.md."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from em_sam_node.core.em_types import EmResult
from em_sam_node.core.inputs import Increment, Observation
from em_sam_node.mapper.processor import MapperProcessor
from slam_core.checkpoint import CheckpointError, load_checkpoint_arrays, save_arrays
from slam_core.checkpoint import shaped as _shape

FORMAT = 'em_sam_mapper checkpoint'
VERSION = 1
COUNTS = (
    'dropped_observations',
    'before_start_observations',
    'dropped_increments',
    'duplicate_increments',
    'duplicate_observations',
)
_RESULT_ARRAYS = (
    'poses',
    'landmark_ids',
    'positions',
    'covariances',
    'weights',
    'moveable',
    'num_observations',
    'weight_history',
    'gated',
    'noise_scale',
    'final_noise_scale',
)
__all__ = ['CheckpointError', 'load_checkpoint', 'save_checkpoint', 'state_arrays']


def _observation_arrays(items: list[Observation], prefix: str) -> dict[str, np.ndarray]:
    return {
        f'{prefix}_stamp_ns': np.array([o.stamp_ns for o in items], dtype=np.int64),
        f'{prefix}_landmark_id': np.array([o.landmark_id for o in items], dtype=np.int64),
        f'{prefix}_z': np.array([o.z for o in items], dtype=float).reshape(-1, 2),
        f'{prefix}_cov': np.array([o.covariance for o in items], dtype=float).reshape(-1, 2, 2),
    }


def state_arrays(mapper: MapperProcessor) -> dict[str, np.ndarray]:
    """Return the processor's state as named arrays (what save_checkpoint writes)."""
    count = len(mapper.increments)
    meta: dict[str, Any] = {
        'format': FORMAT,
        'version': VERSION,
        'counts': {name: int(getattr(mapper, name)) for name in COUNTS},
        'result_keyframes': mapper.result_keyframes,
    }
    arrays: dict[str, np.ndarray] = {
        'stamps_ns': np.array(mapper.stamps_ns, dtype=np.int64),
        'odom_poses': np.array(mapper.odom_poses, dtype=float).reshape(-1, 3),
        'increment_u': np.array([i.u for i in mapper.increments], dtype=float).reshape(count, 3),
        'increment_cov': np.array([i.covariance for i in mapper.increments], dtype=float).reshape(
            count, 3, 3
        ),
        'increment_reset': np.array([i.reset for i in mapper.increments], dtype=bool),
        'observation_keyframe': np.array([k for k, _ in mapper.observations], dtype=np.int64),
        'seen_observations': np.array(sorted(mapper.seen_observations), dtype=np.int64).reshape(
            -1, 2
        ),
        **_observation_arrays([o for _, o in mapper.observations], 'observation'),
        **_observation_arrays(mapper.pending, 'pending'),
    }
    result = mapper.result
    if result is not None:
        meta['result'] = {
            'mode': result.mode,
            'em_iterations': result.em_iterations,
            'converged': bool(result.converged),
            'num_pieces': result.num_pieces,
            'odometry_calibration': [float(v) for v in result.odometry_calibration],
        }
        for name in _RESULT_ARRAYS:
            arrays[f'result_{name}'] = np.asarray(getattr(result, name))
    arrays['meta'] = np.array(json.dumps(meta))
    return arrays


def save_checkpoint(mapper: MapperProcessor, path: Path) -> None:
    """Write the processor's state to ``path`` atomically (temp file, fsync, rename)."""
    arrays = state_arrays(mapper)
    meta = json.loads(str(arrays.pop('meta')))
    save_arrays(path, arrays, meta)


def _observations(arrays: dict[str, np.ndarray], prefix: str) -> list[Observation]:
    stamps = _shape(arrays, f'{prefix}_stamp_ns', (None,))
    count = len(stamps)
    ids = _shape(arrays, f'{prefix}_landmark_id', (count,))
    z = _shape(arrays, f'{prefix}_z', (count, 2))
    cov = _shape(arrays, f'{prefix}_cov', (count, 2, 2))
    return [
        Observation(int(stamps[i]), int(ids[i]), z[i].copy(), cov[i].copy()) for i in range(count)
    ]


def _result(arrays: dict[str, np.ndarray], meta: dict[str, Any], keyframes: int) -> EmResult:
    info = meta['result']
    poses = _shape(arrays, 'result_poses', (keyframes, 3))
    ids = _shape(arrays, 'result_landmark_ids', (None,))
    count = len(ids)
    history = _shape(arrays, 'result_weight_history', (None, count))
    return EmResult(
        mode=str(info['mode']),
        poses=poses,
        landmark_ids=ids,
        positions=_shape(arrays, 'result_positions', (count, 2)),
        covariances=_shape(arrays, 'result_covariances', (count, 2, 2)),
        weights=_shape(arrays, 'result_weights', (count,)),
        moveable=_shape(arrays, 'result_moveable', (count,)).astype(bool),
        num_observations=_shape(arrays, 'result_num_observations', (count,)),
        weight_history=history,
        gated=_shape(arrays, 'result_gated', (None,)).astype(bool),
        sightings={},
        snapshots={},
        em_iterations=int(info['em_iterations']),
        converged=bool(info['converged']),
        num_pieces=int(info['num_pieces']),
        noise_scale=_shape(arrays, 'result_noise_scale', (2,)),
        final_noise_scale=_shape(arrays, 'result_final_noise_scale', (2,)),
        odometry_calibration=tuple(float(v) for v in info['odometry_calibration']),
    )


def _restore(mapper: MapperProcessor, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
    stamps = _shape(arrays, 'stamps_ns', (None,))
    keyframes = len(stamps)
    if keyframes and np.any(np.diff(stamps) <= 0):
        raise ValueError('keyframe stamps do not increase')
    odom_poses = _shape(arrays, 'odom_poses', (keyframes, 3))
    count = max(keyframes - 1, 0)
    u = _shape(arrays, 'increment_u', (count, 3))
    cov = _shape(arrays, 'increment_cov', (count, 3, 3))
    reset = _shape(arrays, 'increment_reset', (count,))
    observations = _observations(arrays, 'observation')
    attached = _shape(arrays, 'observation_keyframe', (len(observations),))
    if len(attached) and (attached.min() < 0 or attached.max() >= keyframes):
        raise ValueError(f'an observation is attached to a keyframe outside 0..{keyframes - 1}')
    seen = _shape(arrays, 'seen_observations', (None, 2))
    result_keyframes = int(meta['result_keyframes'])
    if not 0 <= result_keyframes <= keyframes:
        raise ValueError(f'solution of {result_keyframes} keyframes, but {keyframes} are held')
    result = _result(arrays, meta, result_keyframes) if 'result' in meta else None
    counts = {name: int(meta['counts'][name]) for name in COUNTS}
    mapper.stamps_ns = [int(s) for s in stamps]
    mapper.odom_poses = [p.copy() for p in odom_poses]
    mapper.increments = [
        Increment(
            int(stamps[i]),
            int(stamps[i + 1]),
            u[i].copy(),
            cov[i].copy(),
            odom_poses[i].copy(),
            odom_poses[i + 1].copy(),
            bool(reset[i]),
        )
        for i in range(count)
    ]
    mapper.observations = [(int(k), o) for k, o in zip(attached, observations, strict=True)]
    mapper.pending = _observations(arrays, 'pending')
    mapper.seen_observations = {(int(s), int(i)) for s, i in seen}
    mapper.result = result
    mapper.result_data = None
    mapper.result_keyframes = result_keyframes if result is not None else 0
    for name, value in counts.items():
        setattr(mapper, name, value)


def load_checkpoint(mapper: MapperProcessor, path: Path) -> None:
    """Restore the processor's state from ``path``; CheckpointError names what is wrong."""
    load_checkpoint_arrays(
        path, FORMAT, VERSION, 'mapper', lambda arrays, meta: _restore(mapper, arrays, meta)
    )
