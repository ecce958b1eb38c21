"""The loop scene at the measurement level (paper 001's Fig. 6) and its map metrics.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from slam_evaluation.monoslam_metrics import pose_errors
from slam_evaluation.monoslam_pipeline import (
    MeasurementFrame,
    VariantRecord,
    run_variant,
    simulation_frames,
)
from slam_evaluation.monoslam_runs import TARGET_NOISE_SEED_OFFSET, Settings
from slam_evaluation.shadow_runs import camera_model
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import DynamicSceneRun, simulate_dynamic_scene

REMATCH_FRAMES = 5
"""A feature back in view counts as re-matched when measured within this many frames."""
CLOSED_FRACTION = 0.5
"""The last second's error must be at most this share of the far side's largest."""
LOOP_AWAY_S = 6.0
"""How long the camera stays turned away (at least 5 s)."""
LOOP_DURATION_S = 20.0


@dataclass(frozen=True)
class LoopRun:
    """One run: its scene, frames, the variant's record and the loop's metrics."""

    seed: int
    movers: bool
    variant: str
    scene: DynamicSceneConfig
    frames: Sequence[MeasurementFrame]
    record: VariantRecord
    metrics: dict[str, Any]


def loop_scene(settings: Settings, movers: bool, away_s: float) -> DynamicSceneConfig:
    """Return the Fig. 5 scene of ``settings`` with the loop, with or without movers."""
    scene = dataclasses.replace(settings.scene(), loop_away_s=away_s, keep_track_ids=True)
    return scene if movers else dataclasses.replace(scene, objects=0)


def run_loop(
    settings: Settings, seed: int, movers: bool, variant: str, away_s: float = LOOP_AWAY_S
) -> LoopRun:
    """Simulate ``seed``'s loop scene and run ``variant`` over it."""
    scene = loop_scene(settings, movers, away_s)
    run = simulate_dynamic_scene(seed, scene)
    markers = settings.markers()
    rng = np.random.default_rng(TARGET_NOISE_SEED_OFFSET + seed)
    frames = simulation_frames(run, markers, rng=rng)
    record = run_variant(variant, frames, camera_model(run), settings.pipeline(markers))
    return LoopRun(seed, movers, variant, scene, frames, record, loop_metrics(run, frames, record))


def loop_frames(scene: DynamicSceneConfig) -> dict[str, int]:
    """Return the loop's frame indices 'start', 'away', 'return' and 'back'."""
    loop = scene.loop
    if loop is None:
        raise ValueError('the scene has no loop (loop_away_s = 0)')
    rate = scene.rate_hz
    return {
        'start': round(loop.start_s * rate),
        'away': round((loop.start_s + loop.turn_s) * rate),
        'return': round((loop.start_s + loop.turn_s + loop.away_s) * rate),
        'back': round(loop.back_s * rate),
    }


def position_errors(record: VariantRecord, frames: Sequence[MeasurementFrame]) -> np.ndarray:
    """Return the camera centre error (K,) m per frame, NaN without a pose."""
    return np.asarray(np.linalg.norm(pose_errors(record, frames)[:, :3], axis=1))


def loop_metrics(
    run: DynamicSceneRun, frames: Sequence[MeasurementFrame], record: VariantRecord
) -> dict[str, Any]:
    """Return the metrics of one loop run (re-matched, duplicates, closed, lost)."""
    marks = loop_frames(run.config)
    rate = round(run.config.rate_hz)
    visible = [set(frame.point_ids.tolist()) for frame in run.frames]
    before = range(max(0, marks['start'] - rate), marks['start'] + 1)
    mapped = set().union(*(record.measured_ids[k] for k in before))
    returned, entries = 0, []
    for feature_id in sorted(mapped):
        track_point = run.track_point.get(feature_id)
        if track_point is None:
            continue
        point = int(track_point)
        left = any(point not in visible[k] for k in range(marks['away'], marks['return']))
        entry = next(
            (k for k in range(marks['return'], len(frames))
             if point in visible[k] and point not in visible[k - 1]),
            None,
        )  # fmt: skip
        if not left or entry is None:
            continue
        returned += 1
        window = range(entry, min(entry + REMATCH_FRAMES + 1, len(frames)))
        found = next((k for k in window if feature_id in record.measured_ids[k]), None)
        if found is not None:
            entries.append(found)
    by_point: dict[int, int] = {}
    for map_point in record.map_points:
        world = int(run.track_point.get(map_point.id, -1 - map_point.id))
        by_point[world] = by_point.get(world, 0) + 1
    duplicates = sum(count - 1 for count in by_point.values())
    counts = rematch_metrics(len(mapped), returned, entries, len(record.map_points), duplicates)
    return {**counts, **trajectory_metrics(record, frames, marks, rate)}


def rematch_metrics(
    mapped: int, returned: int, entries: list[int], map_points: int, duplicates: int
) -> dict[str, Any]:
    """Return the map's loop metrics from the counts of features, comebacks and points."""
    return {
        'mapped_before_turn': mapped,
        'returned': returned,
        'rematched': len(entries),
        'rematched_share': len(entries) / returned if returned else math.nan,
        'first_rematch_frame': min(entries) if entries else None,
        'map_points': map_points,
        'duplicates': duplicates,
        'duplicate_share': duplicates / map_points if map_points else 0.0,
    }


def trajectory_metrics(
    record: VariantRecord, frames: Sequence[MeasurementFrame], marks: dict[str, int], rate: int
) -> dict[str, Any]:
    """Return the loop's trajectory metrics: far side, last second, closed, lost, ATE."""
    errors = position_errors(record, frames)
    far = errors[marks['away'] : marks['return']]
    far_max = float(np.nanmax(far)) if np.any(np.isfinite(far)) else math.nan
    last = errors[-rate:]
    last_rms = float(np.sqrt(np.nanmean(last**2))) if np.any(np.isfinite(last)) else math.nan
    tracked = np.isfinite(errors)
    first = int(np.argmax(tracked)) if np.any(tracked) else len(errors)
    untracked_after_start = int(np.count_nonzero(~tracked[first:]))
    lost = bool(record.lost_frames) or untracked_after_start > 0 or not np.any(tracked)
    return {
        'far_side_max_m': far_max,
        'last_second_rms_m': last_rms,
        'closed': bool(last_rms <= CLOSED_FRACTION * far_max),
        'lost': lost,
        'lost_frames': list(record.lost_frames),
        'ate_m': float(np.sqrt(np.nanmean(errors**2))) if np.any(tracked) else math.nan,
        'frames': marks,
    }


def map_history(record: VariantRecord, rate_hz: float) -> dict[str, np.ndarray]:
    """Return per frame (K,) the map's counts: in the state, measured, searched in vain,
    re-matched, deleted, evicted."""
    count = len(record.measured_ids)
    last_seen: dict[int, int] = {}
    rematched = np.zeros(count, dtype=np.int64)
    rate_frames = round(rate_hz)
    for k, ids in enumerate(record.measured_ids):
        rematched[k] = sum(1 for i in ids if i in last_seen and k - last_seen[i] > rate_frames)
        for i in ids:
            last_seen[i] = k
    deleted, evicted = np.zeros(count, dtype=np.int64), np.zeros(count, dtype=np.int64)
    for frame, _, why in record.removals:
        if why in ('failed', 'revoked'):
            deleted[frame] += 1
        elif why == 'evicted':
            evicted[frame] += 1
    return {
        'state': np.asarray(record.state_features, dtype=np.int64),
        'measured': np.array([len(ids) for ids in record.measured_ids], dtype=np.int64),
        'searched': np.array([len(ids) for ids in record.searched_ids], dtype=np.int64),
        'rematched': np.cumsum(rematched),
        'deleted': np.cumsum(deleted),
        'evicted': np.cumsum(evicted),
    }
