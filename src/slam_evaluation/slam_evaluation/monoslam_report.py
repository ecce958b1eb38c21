"""monoslam_evaluate's report: totals per variant, the ATE ratios between variants and the
acceptance points (the content of ``monoslam_eval.json``), and the printed summary.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from slam_evaluation.monoslam_metrics import (
    DIVERGED_ATE_M,
    FloatArray,
    nees_by_frame,
    nees_summary,
)
from slam_evaluation.monoslam_pipeline import (
    VARIANT_TITLES,
)
from slam_evaluation.monoslam_runs import TARGET_NOISE_SEED_OFFSET, Collected, Settings

C_OVER_A_MAX = 1.2
B_OVER_A_MIN = 3.0


def safe_ratio(numerator: float, denominator: float) -> float:
    """numerator / denominator, NaN unless the denominator is > 0."""
    return numerator / denominator if denominator > 0 else math.nan


def finite_mean(values: Sequence[float | None]) -> float:
    """The mean of the finite values (None and NaN left out); NaN if there is none."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def variant_totals(
    per_seed: Sequence[Mapping[str, Any]], nees_values: FloatArray
) -> dict[str, Any]:
    """Return one variant's aggregates over seeds."""
    totals: dict[str, Any] = {
        'seeds': len(per_seed),
        'ate_m_mean': finite_mean([s['ate_m'] for s in per_seed]),
        'ate_sim3_m_mean': finite_mean([s['ate_sim3_m'] for s in per_seed]),
        'sim3_scale_mean': finite_mean([s['sim3_scale'] for s in per_seed]),
        'diverged': sum(s['diverged'] for s in per_seed),
        'map_rms_m_mean': finite_mean([s['map_rms_m'] for s in per_seed]),
        'map_median_m_mean': finite_mean([s['map_median_m'] for s in per_seed]),
        'dynamic_in_map': sum(s['dynamic_in_map'] for s in per_seed),
        'dynamic_entered_map': sum(s['dynamic_entered_map'] for s in per_seed),
        **nees_summary(nees_values),
        'ms_per_frame_mean': finite_mean([s['ms_per_frame'] for s in per_seed]),
    }
    if per_seed and 'shadow' in per_seed[0]:
        keys = per_seed[0]['shadow']
        totals['shadow'] = {k: sum(s['shadow'][k] for s in per_seed) for k in keys}
    return totals


def ratio_summary(
    numerator: Sequence[Mapping[str, Any]] | None,
    denominator: Sequence[Mapping[str, Any]] | None,
    key: str,
) -> dict[str, Any] | None:
    """Return mean ``key`` of the numerator runs / mean of the denominator runs over the seeds
    both ran, and per seed (runs: per seed dicts with 'seed', ``key`` and 'diverged'); None
    if either is missing."""
    if numerator is None or denominator is None:
        return None
    base = {s['seed']: s for s in denominator}
    pairs = [(s, base[s['seed']]) for s in numerator if s['seed'] in base]
    ratios = [
        {
            'seed': s['seed'],
            'ratio': safe_ratio(s[key], b[key]),
            'diverged': s['diverged'],
        }
        for s, b in pairs
    ]
    return {
        'ratio_of_means': safe_ratio(
            finite_mean([s[key] for s, _ in pairs]), finite_mean([b[key] for _, b in pairs])
        ),
        'mean_of_ratios': finite_mean([r['ratio'] for r in ratios]),
        'per_seed': ratios,
    }


def acceptance(ratios: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Return the acceptance points (module docstring) with value, target, seeds meeting the
    target on their own, and the verdict."""
    points = []
    if (c_over_a := ratios.get('c_over_a')) is not None:
        value, seeds = c_over_a['ratio_of_means'], c_over_a['per_seed']
        meeting = [r['ratio'] <= C_OVER_A_MAX for r in seeds]
        passed = value <= C_OVER_A_MAX
        points.append(_point('ATE(c)/ATE(a)', f'<= {C_OVER_A_MAX:g}', value, meeting, passed))
    if (b_over_a := ratios.get('b_over_a')) is not None:
        value, seeds = b_over_a['ratio_of_means'], b_over_a['per_seed']
        meeting = [r['ratio'] >= B_OVER_A_MIN or r['diverged'] for r in seeds]
        passed = value >= B_OVER_A_MIN or (bool(seeds) and all(r['diverged'] for r in seeds))
        target = f'>= {B_OVER_A_MIN:g} or diverges'
        points.append(_point('ATE(b)/ATE(a)', target, value, meeting, passed))
    return points


def _point(
    name: str, target: str, value: float, meeting: Sequence[bool], passed: bool
) -> dict[str, Any]:
    return {
        'name': name,
        'target': target,
        'value': value,
        'seeds_meeting': f'{sum(meeting)}/{len(meeting)}',
        'passed': bool(passed),
    }


def report(settings: Settings, collected: Collected, wall_s: float) -> dict[str, Any]:
    """Return the JSON report: configuration, per variant totals and seeds, curves,
    ratios, acceptance, failures and run time."""
    variants, curves = {}, {}
    for variant, per_seed in collected.per_seed.items():
        values = np.array(collected.nees[variant])
        variants[variant] = {
            'title': VARIANT_TITLES[variant],
            'totals': variant_totals(per_seed, values),
            'per_seed': per_seed,
        }
        errors = np.array(collected.position_error[variant])
        curves[variant] = {
            'ate_rms_m': np.sqrt(np.nanmean(errors**2, axis=0)),
            **{f'nees_{k}': v for k, v in nees_by_frame(values).items()},
        }
    per_variant, base = collected.per_seed, collected.per_seed.get('a')
    ratios = {
        name: ratio_summary(per_variant.get(numerator), base, 'ate_m')
        for name, numerator in (('c_over_a', 'c'), ('b_over_a', 'b'))
    }
    ratios_sim3 = {
        name: ratio_summary(per_variant.get(numerator), base, 'ate_sim3_m')
        for name, numerator in (('c_over_a', 'c'), ('b_over_a', 'b'))
    }
    markers, scene = settings.markers(), settings.scene()
    frames = sum(collected.frames.values())
    filter_s = sum(collected.filter_s.values())
    return {
        'config': {
            'seeds': list(settings.seeds),
            'variants': list(settings.variants),
            'scene': dataclasses.asdict(scene),
            'known_markers': [
                {'id': m.marker_id, 'side_m': m.side_m, 'centre_m': m.centre_m} for m in markers
            ],
            'known_board': list(settings.known_board) if settings.known_board else None,
            'pipeline': dataclasses.asdict(settings.pipeline(markers)),
            'diverged_ate_m': DIVERGED_ATE_M,
            'target_noise_seed': f'{TARGET_NOISE_SEED_OFFSET} + seed',
        },
        'variants': variants,
        'ratios': {k: v for k, v in ratios.items() if v is not None},
        'ratios_sim3': {k: v for k, v in ratios_sim3.items() if v is not None},
        'acceptance': acceptance({k: v for k, v in ratios.items() if v is not None}),
        'curves': {'rate_hz': scene.rate_hz, **curves},
        'failures': collected.failures,
        'runtime': {
            'wall_s': wall_s,
            'filter_s': filter_s,
            'frames': frames,
            'filter_ms_per_frame': 1e3 * filter_s / max(frames, 1),
        },
    }


# --- summary ---------------------------------------------------------------------------------


def number_text(value: float | None, digits: int = 3) -> str:
    """A table cell: the value with ``digits`` decimals (exponent form from 1e5), '--' if
    it is missing or not finite."""
    if value is None or not math.isfinite(value):
        return '--'
    return f'{value:.{digits}f}' if abs(value) < 1e5 else f'{value:.1e}'


SUMMARY_COLUMNS = (
    ('ATE m', 'ate_m_mean', 3),
    ('sim3 m', 'ate_sim3_m_mean', 3),
    ('scale', 'sim3_scale_mean', 2),
    ('div', 'diverged', 0),
    ('map rms', 'map_rms_m_mean', 3),
    ('map med', 'map_median_m_mean', 3),
    ('dyn', 'dynamic_entered_map', 0),
    ('NEES', 'nees_mean', 1),
    ('band', 'frames_in_band', 2),
    ('ms/f', 'ms_per_frame_mean', 1),
)
"""The summary table's columns: header, key in a variant's totals, decimals."""


def summary_text(content: Mapping[str, Any]) -> str:
    """Return the printed summary of a report: one row per variant, Shadow numbers, ratios
    and PASS/FAIL per acceptance point."""
    config = content['config']
    pipeline = config['pipeline']
    gate = pipeline['shadow_max_pose_sigma']
    rule = pipeline['shadow']['classifier']['unchecked_directions']
    board = config.get('known_board')
    known = f'board {board[0]}x{board[1]}' if board else 'one target'
    lines = [
        f'MonoSLAM Fig. 5, seeds {config["seeds"]}, {config["scene"]["duration_s"]:g} s; '
        f'known points: {known}; Shadow pose gate {gate[0]:g} m, {gate[1]:g} rad; '
        f'STATIC rule: {rule} unchecked direction(s)',
        f'  {"variant":36s}' + ''.join(f'{header:>9s}' for header, _, _ in SUMMARY_COLUMNS),
    ]
    for variant, data in content['variants'].items():
        totals = data['totals']
        cells = ''.join(
            f'{number_text(totals[key], digits):>9s}' for _, key, digits in SUMMARY_COLUMNS
        )
        lines.append(f'  ({variant}) {data["title"]:32s}{cells}')
        if 'shadow' in totals:
            shadow = totals['shadow']
            lines.append(
                f'      Shadow: {shadow["handovers"]} handovers ({shadow["handovers_moving"]} '
                f'moving, {shadow["handovers_refused"]} refused); frames processed '
                f'{shadow["frames_processed"]}, skipped by the pose gate '
                f'{shadow["frames_skipped_pose_gate"]}, without a pose '
                f'{shadow["frames_without_pose"]}'
            )
    diagnostics = [
        text
        for text, active in (
            ('the Shadow filter gets the TRUE camera poses', pipeline['shadow_poses'] == 'truth'),
            ('handovers of moving features dropped by ground truth', pipeline['oracle_handovers']),
        )
        if active
    ]
    if diagnostics:
        lines.append(f'  DIAGNOSTIC BOUND, not the system: {"; ".join(diagnostics)}')
    lines.append(
        '  (means over seeds; div: diverged seeds; map: static map point error; dyn: moving '
        'features that entered the map; band: share of frames in the NEES 95 % band)'
    )
    aligned = content['ratios_sim3']
    if aligned:
        ratios = ', '.join(
            f'{name}: {number_text(r["ratio_of_means"], 2)}' for name, r in aligned.items()
        )
        lines.append(f'  after sim(3) alignment: {ratios}')
    for point in content['acceptance']:
        verdict = 'PASS' if point['passed'] else 'FAIL'
        value = number_text(point['value'], 2)
        lines.append(
            f'  {point["name"]:16s} {value:>8s}  target {point["target"]:18s}'
            f' seeds meeting {point["seeds_meeting"]:6s} {verdict}'
        )
    for failure in content['failures']:
        lines.append(
            f'  FAILED RUN seed {failure["seed"]} ({failure["variant"]}): {failure["error"]}'
        )
    return '\n'.join(lines)
