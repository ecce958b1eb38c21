"""A MonoSlam filter's whole state as arrays and JSON, its restoration, and the resume gap.

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam, _Handover
from monoslam_shadow_node.monoslam.core.monoslam_model import (
    CAMERA_SIZE,
    EUCLIDEAN_SIZE,
    INVERSE_DEPTH_SIZE,
    Q_SLICE,
    R_SLICE,
    predict_camera,
)
from monoslam_shadow_node.monoslam.core.monoslam_state import FeatureBlock
from monoslam_shadow_node.monoslam.core.monoslam_types import TRACKING, WAITING, MapPoint
from slam_core.camera import CameraModel
from slam_core.checkpoint import shaped
from slam_core.geometry.quaternion import world_angle_jacobian

_RECORD = (
    'added_frame',
    'last_seen_frame',
    'attempts',
    'successes',
    'consecutive_failures',
    'searches',
    'found',
)
SOURCES = ('start', 'new', 'handover')
NOISE_FIELDS = ('pixel_sigma_px', 'tracking_offset_px', 'tracking_offset_time_s')
"""The tracking noise in force when saved: with ``estimate_noise`` it was estimated, and the
restored filter takes it (its features' offset states were made for it)."""


def _ints(values: Any) -> np.ndarray:
    return np.array(list(values), dtype=np.int64)


def filter_state(slam: MonoSlam) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Return the filter's state as arrays and JSON values (module docstring)."""
    state = slam._state
    features = state.features
    views = slam._views._views
    retired = list(slam._retired.values())
    handovers = list(slam._handovers.values())
    camera = slam.camera
    meta: dict[str, Any] = {
        'camera': {
            'width': camera.width,
            'height': camera.height,
            'distortion_model': camera.distortion_model,
        },
        'known_points': sorted([k, *map(float, p)] for k, p in slam._known.items()),
        'status': slam._status,
        'frame': slam._frame,
        'last_stamp_ns': slam._last_stamp_ns,
        'idle_frames': slam._idle_frames,
        'known_rejected_frames': slam._known_rejected_frames,
        'known_rejected': list(slam._known_rejected),
        'rng': slam._rng.bit_generator.state,
        'tracking_noise': {name: getattr(slam.config, name) for name in NOISE_FIELDS},
        'features': [
            {
                'id': f.id,
                'size': f.size,
                'offset_size': f.offset_size,
                'source': f.source,
                'probation': f.probation,
                'cleared': f.cleared,
                **{name: getattr(f, name) for name in _RECORD},
            }
            for f in features
        ],
        'retired': [
            {
                'id': p.id,
                'parametrization': p.parametrization,
                'source': p.source,
                'covariance': p.covariance is not None,
            }
            for p in retired
        ],
        'handover_frames': [h.frame for h in handovers],
        'views_previous': sorted(slam._views._previous),
        'owned_ids': sorted(slam._owned_ids),
        'moving_ids': list(slam._moving_ids),
        'revoked_by_shadow': list(slam._revoked_by_shadow),
    }
    arrays = {
        'camera_k': camera.K.copy(),
        'camera_d': camera.D.copy(),
        'x': state.x.copy(),
        'p': state.p.copy(),
        'feature_reference': np.array(
            [f.reference if f.reference is not None else np.eye(3) for f in features]
        ).reshape(-1, 3, 3),
        'feature_first_ray': np.array(
            [f.first_ray if f.first_ray is not None else np.zeros(3) for f in features]
        ).reshape(-1, 3),
        'retired_position': np.array([p.position for p in retired]).reshape(-1, 3),
        'retired_covariance': np.array(
            [p.covariance if p.covariance is not None else np.zeros((3, 3)) for p in retired]
        ).reshape(-1, 3, 3),
        'handover_id': _ints(h.id for h in handovers),
        'handover_position': np.array([h.position for h in handovers]).reshape(-1, 3),
        'handover_covariance': np.array([h.covariance for h in handovers]).reshape(-1, 3, 3),
        'view_id': _ints(views),
        'view_centre': np.array([v[0] for v in views.values()]).reshape(-1, 3),
        'view_rotation': np.array([v[1] for v in views.values()]).reshape(-1, 3, 3),
        'view_pixel': np.array([v[2] for v in views.values()]).reshape(-1, 2),
    }
    return arrays, meta


def saved_camera(arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> CameraModel:
    """Return the camera the state was saved with (ValueError when it is not a camera)."""
    info = meta['camera']
    return CameraModel(
        int(info['width']),
        int(info['height']),
        shaped(arrays, 'camera_k', (3, 3)),
        shaped(arrays, 'camera_d', (None,)),
        str(info['distortion_model']),
    )


def _blocks(
    meta: dict[str, Any], arrays: dict[str, np.ndarray], offset: int, mixed: bool = False
) -> list[FeatureBlock]:
    """The feature blocks laid out from x[13] on, checked (ValueError names the culprit)."""
    items = meta['features']
    count = len(items)
    references = shaped(arrays, 'feature_reference', (count, 3, 3))
    rays = shaped(arrays, 'feature_first_ray', (count, 3))
    blocks, start = [], CAMERA_SIZE
    for k, item in enumerate(items):
        size, offset_size = int(item['size']), int(item['offset_size'])
        where = f'feature {item["id"]}'
        if size not in (EUCLIDEAN_SIZE, INVERSE_DEPTH_SIZE):
            raise ValueError(f'{where}: block of {size} states, expected 3 or 6')
        if offset_size not in ((0, 2) if mixed else (offset,)):  # 2: one per image axis
            raise ValueError(
                f'{where}: tracker offset of {offset_size} states, but this filter keeps '
                f"{offset} (tracking_offset_px differs from the saved run's)"
            )
        if item['source'] not in SOURCES:
            raise ValueError(
                f'{where}: source {item["source"]!r}, expected one of {", ".join(SOURCES)}'
            )
        reference = references[k].copy() if size == INVERSE_DEPTH_SIZE else None
        block = FeatureBlock(
            int(item['id']),
            start,
            size,
            reference,
            str(item['source']),
            0,
            0,
            probation=bool(item['probation']),
            # snapshots from before 'cleared': a feature not handed over was undecided
            cleared=bool(item.get('cleared', item['source'] == 'handover')),
            offset_size=offset_size,
            first_ray=rays[k].copy(),
        )
        for name in _RECORD:
            setattr(block, name, int(item[name]))
        blocks.append(block)
        start += block.extent
    if len({b.id for b in blocks}) != len(blocks):
        raise ValueError('two features have the same track id')
    return blocks


def _retired(meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> dict[int, MapPoint]:
    items = meta['retired']
    positions = shaped(arrays, 'retired_position', (len(items), 3))
    covariances = shaped(arrays, 'retired_covariance', (len(items), 3, 3))
    return {
        int(item['id']): MapPoint(
            int(item['id']),
            positions[k].copy(),
            covariances[k].copy() if item['covariance'] else None,
            str(item['parametrization']),
            False,
            str(item['source']),
        )
        for k, item in enumerate(items)
    }


def restore_filter(slam: MonoSlam, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
    """Put a saved state into ``slam``; ValueError naming what does not fit."""
    known = sorted([k, *map(float, p)] for k, p in slam._known.items())
    if [[int(k), *map(float, p)] for k, *p in meta['known_points']] != known:
        raise ValueError(
            "its initialization target (the known points) differs from this node's: check "
            'the target_* parameters'
        )
    status = meta['status']
    if status not in (WAITING, TRACKING):
        raise ValueError(f'tracking state {status!r}, expected {WAITING} or {TRACKING}')
    if slam.config.estimate_noise and 'tracking_noise' in meta:
        noise = meta['tracking_noise']
        slam.config = dataclasses.replace(
            slam.config,
            pixel_sigma_px=float(noise['pixel_sigma_px']),
            tracking_offset_px=float(noise['tracking_offset_px']),
            tracking_offset_time_s=float(noise['tracking_offset_time_s']),
        )
    offset = 2 if slam.config.offset_states else 0
    blocks = _blocks(meta, arrays, offset, mixed=slam.config.estimate_noise)
    n = blocks[-1].start + blocks[-1].extent if blocks else CAMERA_SIZE
    x = shaped(arrays, 'x', (None,))
    if (len(x) or status == TRACKING or blocks) and len(x) != n:
        raise ValueError(f'state of {len(x)} values, but the camera and features take {n}')
    p = shaped(arrays, 'p', (len(x), len(x)))
    if not np.allclose(p, p.T, rtol=0.0, atol=1e-9 * max(1.0, float(np.abs(p).max(initial=0)))):
        raise ValueError('covariance is not symmetric')
    handovers = shaped(arrays, 'handover_id', (None,))
    count = len(handovers)
    positions = shaped(arrays, 'handover_position', (count, 3))
    covariances = shaped(arrays, 'handover_covariance', (count, 3, 3))
    frames = meta['handover_frames']
    if len(frames) != count:
        raise ValueError(f'{len(frames)} handover frames for {count} handovers')
    view_ids = shaped(arrays, 'view_id', (None,))
    centres = shaped(arrays, 'view_centre', (len(view_ids), 3))
    rotations = shaped(arrays, 'view_rotation', (len(view_ids), 3, 3))
    pixels = shaped(arrays, 'view_pixel', (len(view_ids), 2))
    last_stamp = meta['last_stamp_ns']
    retired = _retired(meta, arrays)
    rng = np.random.default_rng()
    rng.bit_generator.state = meta['rng']
    state = slam._state
    state.x, state.p, state.features = x.copy(), p.copy(), blocks
    slam._retired = retired
    slam._handovers = {
        int(i): _Handover(int(i), positions[k].copy(), covariances[k].copy(), int(frames[k]))
        for k, i in enumerate(handovers)
    }
    slam._views._views = {
        int(i): (centres[k].copy(), rotations[k].copy(), pixels[k].copy())
        for k, i in enumerate(view_ids)
    }
    slam._views._previous = frozenset(int(i) for i in meta['views_previous'])
    slam._owned_ids = {int(i) for i in meta['owned_ids']}
    slam._moving_ids = {int(i): None for i in meta['moving_ids']}
    slam._revoked_by_shadow = [int(i) for i in meta['revoked_by_shadow']]
    slam._frame = int(meta['frame'])
    slam._last_stamp_ns = None if last_stamp is None else int(last_stamp)
    slam._status = status
    slam._idle_frames = int(meta['idle_frames'])
    slam._known_rejected_frames = int(meta['known_rejected_frames'])
    rejected, in_view = meta['known_rejected']
    slam._known_rejected = (int(rejected), int(in_view))
    slam._rng = rng


@dataclass(frozen=True)
class GapVerdict:
    """Whether a resumed filter predicts over the gap, with the predicted sigmas and limits."""

    gap_s: float
    predict: bool
    position_sigma_m: float
    rotation_sigma_rad: float
    position_limit_m: float
    rotation_limit_rad: float

    def describe(self) -> str:
        """Return 'the 0.03 s gap: predicted sigma 0.01 m / 0.02 rad (limits 2 m / 0.18 rad)'."""
        return (
            f'the {self.gap_s:.3f} s gap: predicted sigma {self.position_sigma_m:.3g} m / '
            f'{self.rotation_sigma_rad:.3g} rad (limits {self.position_limit_m:g} m / '
            f'{self.rotation_limit_rad:.3g} rad)'
        )


def rotation_limit_rad(slam: MonoSlam) -> float:
    """The largest orientation sigma a prediction over a gap may have (rad)."""
    camera = slam.camera
    half_view = math.atan(0.5 * min(camera.width / camera.fx, camera.height / camera.fy))
    return half_view / math.sqrt(slam.config.gate)


def gap_verdict(slam: MonoSlam, stamp_ns: int) -> GapVerdict | None:
    """Judge the gap to a frame at ``stamp_ns``; None when not after the last frame."""
    last_ns = slam._last_stamp_ns
    if last_ns is None or stamp_ns <= last_ns:
        return None
    dt_s = (stamp_ns - last_ns) * 1e-9
    config = slam.config
    x, p = slam._state.x[:CAMERA_SIZE], slam._state.p[:CAMERA_SIZE, :CAMERA_SIZE]
    sigmas = config.linear_acceleration_sigma, config.angular_acceleration_sigma
    camera, f, q = predict_camera(x, dt_s, *sigmas)
    predicted = f @ p @ f.T + q
    to_angles = world_angle_jacobian(camera[Q_SLICE])
    rotation = to_angles @ predicted[Q_SLICE, Q_SLICE] @ to_angles.T
    position = predicted[R_SLICE, R_SLICE]
    position_sigma = math.sqrt(max(float(np.linalg.eigvalsh(position)[-1]), 0.0))
    rotation_sigma = math.sqrt(max(float(np.linalg.eigvalsh(rotation)[-1]), 0.0))
    limit = rotation_limit_rad(slam)
    predict = position_sigma <= config.max_position_sigma_m and rotation_sigma <= limit
    return GapVerdict(
        dt_s, predict, position_sigma, rotation_sigma, config.max_position_sigma_m, limit
    )


def relocalise(slam: MonoSlam) -> None:
    """Keep the map, and take the camera's pose from the target again when next in view."""
    slam._status = WAITING
    slam._idle_frames = 0
    slam._known_rejected_frames = 0
