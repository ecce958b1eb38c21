"""monoslam_image_evaluate's report (``monoslam_image_eval.json``) and Markdown table.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from typing import Any

import numpy as np

from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig
from slam_core.arrays import FloatArray
from slam_evaluation import monoslam_runs
from slam_evaluation.monoslam_front_end import MOVING_RADIUS_PX, FrontEndStats
from slam_evaluation.monoslam_image_runs import RUNS, SeedResult, Settings
from slam_evaluation.monoslam_report import (
    TRACKED_SHARE_MIN,
    acceptance_point,
    finite_mean,
    number_text,
    ratio_summary,
    tracking_summary,
)
from slam_sim.core.init_target import InitTarget

IMAGE_OVER_MEASUREMENT_MAX = 1.5


def run_totals(runs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Return one filter run's aggregates over seeds (means over finite values)."""
    totals: dict[str, Any] = {'seeds': len(runs)}
    for key in ('ate_m', 'ate_sim3_m', 'sim3_scale', 'ms_per_frame'):
        totals[f'{key}_mean'] = finite_mean([run[key] for run in runs])
    totals['diverged'] = sum(run['diverged'] for run in runs)
    totals['dynamic_entered_map'] = sum(run['dynamic_entered_map'] for run in runs)
    if runs and 'shadow' in runs[0]:
        totals['shadow'] = {k: sum(run['shadow'][k] for run in runs) for k in runs[0]['shadow']}
    return totals


def _runs(per_seed: Sequence[Mapping[str, Any]], level: str, variant: str) -> list[dict[str, Any]]:
    """Return a filter run's metrics per seed, each with its seed."""
    return [
        {'seed': entry['seed'], **entry[level][variant]}
        for entry in per_seed
        if variant in entry.get(level, {})
    ]


def level_ratio(per_seed: Sequence[Mapping[str, Any]], key: str) -> dict[str, Any] | None:
    """Return mean ``key`` of image c / measurement c over the seeds both ran, and per seed."""
    return ratio_summary(_runs(per_seed, 'image', 'c'), _runs(per_seed, 'measurement', 'c'), key)


def image_tracking(per_seed: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Return the frames image c tracked against image a, per seed (``tracking_summary``)."""
    return tracking_summary(_runs(per_seed, 'image', 'c'), _runs(per_seed, 'image', 'a'))


def acceptance(
    ratio: Mapping[str, Any] | None, tracking: Mapping[str, Any]
) -> list[dict[str, Any]]:
    """Return the acceptance points: the ATE ratio with image c tracking, and the tracking."""
    seeds = ratio['per_seed'] if ratio is not None else []
    value = ratio['ratio_of_means'] if ratio is not None else math.nan
    kept = {r['seed']: r['kept'] for r in tracking['per_seed']}
    meeting = [
        r['ratio'] <= IMAGE_OVER_MEASUREMENT_MAX and kept.get(r['seed'], False) for r in seeds
    ]
    passed = math.isfinite(value) and value <= IMAGE_OVER_MEASUREMENT_MAX
    passed = passed and bool(kept) and all(kept.values())
    target = f'<= {IMAGE_OVER_MEASUREMENT_MAX:g}, tracking kept'
    name = 'ATE(c) images / ATE(c) measurements'
    tracked = list(kept.values())
    return [
        acceptance_point(name, target, value, meeting, passed),
        acceptance_point(
            'tracked image (c)/(a)',
            f'>= {TRACKED_SHARE_MIN:g}, never lost',
            tracking['min_share'],
            tracked,
            bool(tracked) and all(tracked),
        ),
    ]


def _pooled(results: Sequence[SeedResult]) -> FrontEndStats:
    pooled = FrontEndStats()
    for result in results:
        for name, value in asdict(result.front_end).items():
            setattr(pooled, name, getattr(pooled, name) + value)
    return pooled


def error_curves(results: Sequence[SeedResult]) -> dict[str, FloatArray]:
    """Return per filter run the position errors (S, K) m, NaN-padded (NaN: no estimate)."""
    length = max((len(r.truth) for r in results), default=0)
    curves = {}
    for level, variant in RUNS:
        name = f'{level} {variant}'
        rows = np.full((len(results), length), np.nan)
        for row, result in zip(rows, results, strict=True):
            if name in result.errors:
                row[: len(result.errors[name])] = result.errors[name]
        curves[name] = rows
    return curves


def rms_over_seeds(values: FloatArray) -> FloatArray:
    """Return per frame (K,) the RMS over seeds of values (S, K) (NaN where none is finite)."""
    finite = np.isfinite(values)
    counts = finite.sum(axis=0)
    sums = np.where(finite, values**2, 0.0).sum(axis=0)
    return np.where(counts > 0, np.sqrt(sums / np.maximum(counts, 1)), np.nan)


def report(settings: Settings, results: Sequence[SeedResult], wall_s: float) -> dict[str, Any]:
    """Return the JSON report: configuration, seeds, totals, ratios, acceptance, curves."""
    per_seed = [result.entry for result in results]
    target = settings.sources[0].target if settings.sources else InitTarget()
    totals: dict[str, Any] = {
        level: {v: run_totals(_runs(per_seed, level, v)) for lv, v in RUNS if lv == level}
        for level in ('image', 'measurement')
    }
    totals['front_end'] = _pooled(results).summary()
    ratios = {key: level_ratio(per_seed, key) for key in ('ate_m', 'ate_sim3_m')}
    tracking = image_tracking(per_seed)
    curves = {name: rms_over_seeds(values) for name, values in error_curves(results).items()}
    rate = settings.sources[0].config.rate_hz if settings.sources else math.nan
    return {
        'config': {
            'sources': [
                {
                    'seed': s.seed,
                    'source': s.name,
                    'frames': s.frame_count,
                    'scene': asdict(s.config),
                }
                for s in settings.sources
            ],
            'pipeline': asdict(settings.pipeline(target)),
            'tracker': asdict(TrackerConfig()),
            'moving_radius_px': MOVING_RADIUS_PX,
            'target_noise_seed': f'{monoslam_runs.TARGET_NOISE_SEED_OFFSET} + seed',
        },
        'per_seed': per_seed,
        'totals': totals,
        'ratio_c': ratios['ate_m'],
        'ratio_c_sim3': ratios['ate_sim3_m'],
        'tracking_c': tracking,
        'acceptance': acceptance(ratios['ate_m'], tracking),
        'curves': {'rate_hz': rate, **{f'{name} rms_m': v for name, v in curves.items()}},
        'failures': [f for entry in per_seed for f in entry.get('failures', [])],
        'runtime': {'wall_s': wall_s},
    }


# --- table -----------------------------------------------------------------------------------


def _ate_cell(run: Mapping[str, Any] | None, key: str) -> str:
    if run is None:
        return 'failed'
    return number_text(run[key]) + ('*' if run['diverged'] else '')


TABLE_HEADER = (
    'seed', 'a ATE', 'b ATE', 'c ATE', 'meas. c ATE', 'c img/meas', 'c/a frames', 'a sim3',
    'b sim3', 'c sim3', 'meas. c sim3', 'features/frame', 'moving %', 'target det. %',
    'corner rms px',
)  # fmt: skip
"""The table's columns: ATE raw (m) of image a, b, c and measurement c, the ratio, the frames
image c tracked / those image a tracked, ATE after the sim(3) alignment (m), and the front
end."""


def _front_cells(front: Mapping[str, Any]) -> list[str]:
    return [
        number_text(front['features_per_frame'], 0),
        number_text(100.0 * front['moving_share'], 1),
        number_text(100.0 * front['detection_rate'], 1),
        number_text(front['corner_rms_px'], 2),
    ]


def _tracked_cell(tracking: Mapping[str, Any] | None) -> str:
    """'c/a' frames tracked at image level, 'lost' when c lost tracking ('--': no image a)."""
    if tracking is None:
        return '--'
    lost = ' lost' if tracking['lost'] else ''
    return f'{tracking["frames_tracked"]}/{tracking["frames_tracked_a"]}{lost}'


def _seed_cells(entry: Mapping[str, Any], tracking: Mapping[str, Any] | None) -> list[str]:
    runs = [entry.get(level, {}).get(variant) for level, variant in RUNS]
    return [
        str(entry['seed']),
        *(_ate_cell(run, 'ate_m') for run in runs),
        number_text(entry['ratio_c']['ate_m'], 2),
        _tracked_cell(tracking),
        *(_ate_cell(run, 'ate_sim3_m') for run in runs),
        *_front_cells(entry['front_end']),
    ]


def _mean_cells(content: Mapping[str, Any]) -> list[str]:
    totals = content['totals']
    runs = [totals[level][variant] for level, variant in RUNS]
    ratio = content['ratio_c']
    return [
        'mean',
        *(number_text(run['ate_m_mean']) for run in runs),
        number_text(ratio['ratio_of_means'] if ratio else None, 2),
        '',
        *(number_text(run['ate_sim3_m_mean']) for run in runs),
        *_front_cells(totals['front_end']),
    ]


def table_text(content: Mapping[str, Any]) -> str:
    """Return the markdown table of a report (a row per seed and the means) with the
    acceptance, the Shadow numbers of image c and the failed runs."""
    rows = [list(TABLE_HEADER), ['---'] * len(TABLE_HEADER)]
    tracking = {r['seed']: r for r in content['tracking_c']['per_seed']}
    rows += [_seed_cells(entry, tracking.get(entry['seed'])) for entry in content['per_seed']]
    rows.append(_mean_cells(content))
    lines = ['| ' + ' | '.join(row) + ' |' for row in rows]
    lines += [
        '',
        'ATE in m (raw: the target fixes the scale; sim3: after the sim(3) alignment); '
        '* diverged (ATE > 1 m, tracking lost or a non-finite estimate). a, b, c: image level; '
        'meas. c: measurement level, same seed and scene. c/a frames: frames image c tracked / '
        'frames image a tracked.',
    ]
    lines += [
        f'{point["name"]} = {number_text(point["value"], 2)} '
        f'(target {point["target"]}; '
        f'seeds meeting {point["seeds_meeting"]}): {"met" if point["passed"] else "NOT met"}'
        for point in content['acceptance']
    ]
    shadow = content['totals']['image']['c'].get('shadow')
    if shadow:
        lines.append(
            f'Image c Shadow filter: {shadow["handovers"]} handovers ({shadow["handovers_moving"]}'
            f' moving, {shadow["handovers_refused"]} refused); frames processed '
            f'{shadow["frames_processed"]}, without a pose {shadow["frames_without_pose"]}, '
            f'pose covariance not finite {shadow["frames_pose_not_finite"]}'
        )
    lines += [
        f'FAILED RUN seed {f["seed"]} ({f["level"]} {f["variant"]}): {f["error"]}'
        for f in content['failures']
    ]
    return '\n'.join(lines)
