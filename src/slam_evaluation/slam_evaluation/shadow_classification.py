"""shadow_evaluate's classification scores (paper 001's Fig. 4)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING, STATIC, STATUS_NAMES
from slam_evaluation.shadow_runs import FilterRecord, IntArray, track_truths, view_parallax_rad
from slam_sim.core.dynamic_scene import DynamicSceneRun


@dataclass(frozen=True)
class Outcome:
    """One track's classification: truth, status, frames to decide (-1: undecided), the deciding
    test's parallax (rad) and baseline (m), the window's, whether parallax allows, and
    whether DYNAMIC because its views fix no static point."""

    track_id: int
    moving: bool
    motion: str
    status: int
    frames_to_decide: int
    decision_parallax_rad: float
    decision_baseline_m: float
    window_parallax_rad: float
    window_baseline_m: float
    parallax_allows: bool
    without_fit: bool = False


def track_outcomes(
    run: DynamicSceneRun, record: FilterRecord, *, window_frames: int, min_parallax_rad: float
) -> list[Outcome]:
    """Return every track's Outcome."""
    centres = np.array([frame.camera_position for frame in run.frames])
    outcomes = []
    for track_id, truth in sorted(track_truths(run).items()):
        parallax, baseline = math.nan, math.nan
        later = truth.first_frame + window_frames
        if truth.last_frame >= later:
            point = run.point_positions[truth.first_frame, truth.point]
            first_centre, later_centre = centres[truth.first_frame], centres[later]
            parallax = view_parallax_rad(point, first_centre, later_centre)
            baseline = float(np.linalg.norm(later_centre - first_centre))
        status, frames, decision_parallax, decision_baseline = PENDING, -1, math.nan, math.nan
        without_fit = False
        if track_id in record.decisions:
            _, decision = record.decisions[track_id]
            status, frames = decision.status, decision.frames_since_first
            decision_parallax, decision_baseline = decision.parallax_rad, decision.baseline_m
            without_fit = status == DYNAMIC and math.isnan(decision.statistic)
        allows = bool(parallax >= min_parallax_rad)  # False for NaN
        outcomes.append(
            Outcome(
                track_id,
                truth.moving,
                truth.motion,
                status,
                frames,
                decision_parallax,
                decision_baseline,
                parallax,
                baseline,
                allows,
                without_fit,
            )
        )
    return outcomes


def status_name(status: int) -> str:
    """Return the name of a status code (its number for codes the core does not name)."""
    return STATUS_NAMES.get(status, str(status))


def confusion_counts(
    outcomes: Iterable[Outcome], *, by_motion: bool = False
) -> dict[str, dict[str, int]]:
    """Return {truth: {status name: n}} (truth by motion kind if ``by_motion``), zeros kept."""
    table: dict[str, dict[str, int]] = {}
    if not by_motion:
        table = {'static': {}, 'moving': {}}
    for outcome in outcomes:
        truth = outcome.motion if by_motion else ('moving' if outcome.moving else 'static')
        row = table.setdefault(truth, {})
        name = status_name(outcome.status)
        row[name] = row.get(name, 0) + 1
    for row in table.values():
        for status in (STATIC, DYNAMIC, PENDING):
            row.setdefault(status_name(status), 0)
    return table


def count_ratio(numerator: int, denominator: int) -> float:
    """numerator / denominator, NaN when the denominator is 0."""
    return numerator / denominator if denominator else math.nan


def classification_rates(table: Mapping[str, Mapping[str, int]]) -> dict[str, float | int]:
    """Return the error rates of a static/moving confusion table."""
    static, moving = table.get('static', {}), table.get('moving', {})
    names = (status_name(STATIC), status_name(DYNAMIC))
    static_decided = sum(static.get(name, 0) for name in names)
    moving_decided = sum(moving.get(name, 0) for name in names)
    static_called_dynamic = static.get(status_name(DYNAMIC), 0)
    moving_called_static = moving.get(status_name(STATIC), 0)
    return {
        'static_called_dynamic': static_called_dynamic,
        'static_called_dynamic_of_decided': count_ratio(static_called_dynamic, static_decided),
        'static_called_dynamic_of_all': count_ratio(static_called_dynamic, sum(static.values())),
        'moving_called_static': moving_called_static,
        'moving_called_static_of_decided': count_ratio(moving_called_static, moving_decided),
        'moving_called_dynamic_of_all': count_ratio(
            moving.get(status_name(DYNAMIC), 0), sum(moving.values())
        ),
        'static_decided_of_all': count_ratio(static_decided, sum(static.values())),
        'moving_decided_of_all': count_ratio(moving_decided, sum(moving.values())),
    }


def latency_summary(outcomes: Sequence[Outcome], *, window_frames: int) -> dict[str, Any]:
    """Return frames to decide (median, p90) and the share decided within ``window_frames``."""
    frames = np.array([o.frames_to_decide for o in outcomes if o.frames_to_decide >= 0])
    within = int(np.count_nonzero(frames <= window_frames))
    return {
        'features': len(outcomes),
        'decided': len(frames),
        'median_frames': float(np.median(frames)) if len(frames) else math.nan,
        'p90_frames': float(np.percentile(frames, 90)) if len(frames) else math.nan,
        'within_window_of_decided': count_ratio(within, len(frames)),
        'within_window_of_all': count_ratio(within, len(outcomes)),
    }


def classification_summary(
    outcomes: Sequence[Outcome], *, window_frames: int, min_baseline_m: float
) -> dict[str, Any]:
    """Return confusion tables, rates and latencies of ``outcomes``."""
    allowed = [o for o in outcomes if o.parallax_allows]
    table = confusion_counts(outcomes)
    latency = {}
    for group, keep in (
        ('all', lambda o: True),
        ('static', lambda o: not o.moving),
        ('moving', lambda o: o.moving),
    ):
        latency[group] = {
            'all_features': latency_summary(
                [o for o in outcomes if keep(o)], window_frames=window_frames
            ),
            'parallax_allows': latency_summary(
                [o for o in allowed if keep(o)], window_frames=window_frames
            ),
        }
    short_baseline = [o for o in allowed if o.window_baseline_m < min_baseline_m]
    return {
        'tracks': len(outcomes),
        'confusion': table,
        'confusion_by_motion': confusion_counts(outcomes, by_motion=True),
        'confusion_parallax_allows': confusion_counts(allowed),
        'rates': classification_rates(table),
        'latency': latency,
        'parallax_allows_with_baseline_below_min': len(short_baseline),
        'dynamic_without_fit': {
            'static': sum(o.without_fit and not o.moving for o in outcomes),
            'moving': sum(o.without_fit and o.moving for o in outcomes),
        },
    }


def moving_called_static_details(
    run: DynamicSceneRun, record: FilterRecord, outcomes: Sequence[Outcome]
) -> list[dict[str, Any]]:
    """Return per moving track called STATIC its displacement (m) and speeds (m/s)."""
    truths = track_truths(run)
    details = []
    for outcome in outcomes:
        if not (outcome.moving and outcome.status == STATIC):
            continue
        truth = truths[outcome.track_id]
        decided_frame = record.decisions[outcome.track_id][0]
        path = run.point_positions[truth.first_frame : decided_frame + 1, truth.point]
        speeds = np.linalg.norm(
            run.point_velocities[truth.first_frame : decided_frame + 1, truth.point], axis=1
        )
        details.append(
            {
                'seed': run.seed,
                'track_id': outcome.track_id,
                'motion': outcome.motion,
                'first_frame': truth.first_frame,
                'decided_frame': decided_frame,
                'frames_to_decide': outcome.frames_to_decide,
                'decision_parallax_deg': math.degrees(outcome.decision_parallax_rad),
                'decision_baseline_m': outcome.decision_baseline_m,
                'true_displacement_m': float(np.linalg.norm(path[-1] - path[0])),
                'true_mean_speed_m_s': float(speeds.mean()),
                'true_max_speed_m_s': float(speeds.max()),
            }
        )
    return details


def status_at(decided: Mapping[int, tuple[int, int]], track_id: int, frame: int) -> int:
    """Return a track's status as of ``frame`` (``decided``: id -> (frame, status))."""
    decided_frame, status = decided.get(track_id, (-1, PENDING))
    return status if 0 <= decided_frame <= frame else PENDING


def status_timeline(
    track_ids_per_frame: Sequence[IntArray], decided: Mapping[int, tuple[int, int]]
) -> IntArray:
    """Return (K, 3) counts of visible PENDING, STATIC, DYNAMIC features per frame."""
    counts = np.zeros((len(track_ids_per_frame), 3), dtype=np.int64)
    column = {PENDING: 0, STATIC: 1, DYNAMIC: 2}
    for index, ids in enumerate(track_ids_per_frame):
        for track_id in ids.tolist():
            counts[index, column.get(status_at(decided, track_id, index), 0)] += 1
    return counts
