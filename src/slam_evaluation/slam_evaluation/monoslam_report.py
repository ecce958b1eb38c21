"""monoslam_evaluate's report (``monoslam_eval.json``), acceptance and printed summary.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam_evaluation.monoslam_metrics import (
    DIVERGED_ATE_M,
    REVOCATION_FRAMES,
    FloatArray,
    nees_by_frame,
    nees_summary,
)
from slam_evaluation.monoslam_pipeline import (
    VARIANT_TITLES,
)
from slam_evaluation.monoslam_runs import TARGET_NOISE_SEED_OFFSET, Collected, Settings

C_OVER_A_MAX = 1.5
"""ATE(c)/ATE(a), the ratio of the means over seeds (the goal is 1.2) ..."""
C_OVER_A_SEED_MAX = 2.0
"""... and on every seed."""
C_OVER_A_GOAL = 1.2
B_OVER_A_MIN = 3.0
TRACKED_SHARE_MIN = 0.95
"""(c) must track at least this share of the frames (a) tracks on the same seed."""


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
    """Return mean ``key`` of numerator / denominator runs over the seeds both ran, and per
    seed; None if either is missing."""
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


def tracking_summary(
    variant: Sequence[Mapping[str, Any]], base: Sequence[Mapping[str, Any]]
) -> dict[str, Any]:
    """Return per seed of (a) the frames the variant tracked against (a)'s, and whether it kept
    tracking (ran, never lost, share >= TRACKED_SHARE_MIN); and the smallest share."""
    runs = {s['seed']: s for s in variant}
    seeds = []
    for b in base:
        run = runs.get(b['seed'])
        tracked = run['frames_tracked'] if run is not None else 0
        lost = run is not None and bool(run['lost_frames'])
        share = safe_ratio(tracked, b['frames_tracked'])
        seeds.append(
            {
                'seed': b['seed'],
                'frames_tracked': tracked,
                'frames_tracked_a': b['frames_tracked'],
                'share': share,
                'lost': lost,
                'ran': run is not None,
                'kept': run is not None and not lost and share >= TRACKED_SHARE_MIN,
            }
        )
    shares = [r['share'] for r in seeds]
    min_share = float(np.min(shares)) if shares else math.nan  # NaN if any share is NaN
    return {'min_share': min_share, 'per_seed': seeds}


def mover_summary(per_seed: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    """Return (c)'s movers in SLAM's map over seeds (outcome sums, latencies); None without (c)."""
    runs = [s for s in per_seed if 'movers' in s]
    if not runs:
        return None
    keys = ('in_time', 'late', 'missed', 'left_view', 'radial', 'removed_early', 'lost_with_map')
    latencies = [v for s in runs for v in s['movers']['latencies']]
    observable = [v for s in runs for v in s['movers']['observable']['latencies']]
    return {
        **{k: sum(s['movers'][k] for s in runs) for k in (*keys, 'entries', 'revoked')},
        'revoked_static': sum(s['movers'].get('revoked_static', 0) for s in runs),
        'latency_median_frames': float(np.median(latencies)) if latencies else math.nan,
        'latency_max_frames': max(latencies) if latencies else math.nan,
        'observable': {
            **{k: sum(s['movers']['observable'][k] for s in runs) for k in keys},
            'latency_median_frames': float(np.median(observable)) if observable else math.nan,
        },
        'per_seed': [{'seed': s['seed'], **s['movers']} for s in runs],
    }


def acceptance(
    ratios: Mapping[str, Any],
    tracking: Mapping[str, Any] | None = None,
    movers: Mapping[str, Any] | None = None,
) -> list[dict[str, Any]]:
    """Return the acceptance points (value, target, seeds meeting it, verdict); ``tracking``
    and ``movers``: (c)'s summaries."""
    points = []
    kept = {r['seed']: r['kept'] for r in tracking['per_seed']} if tracking is not None else {}
    if (c_over_a := ratios.get('c_over_a')) is not None:
        value, seeds = c_over_a['ratio_of_means'], c_over_a['per_seed']
        meeting = [r['ratio'] <= C_OVER_A_SEED_MAX and kept.get(r['seed'], False) for r in seeds]
        passed = value <= C_OVER_A_MAX and bool(kept) and all(kept.values()) and all(meeting)
        target = f'<= {C_OVER_A_MAX:g} (seed <= {C_OVER_A_SEED_MAX:g}), kept'
        points.append(acceptance_point('ATE(c)/ATE(a)', target, value, meeting, passed))
    if tracking is not None:
        meeting = list(kept.values())
        target = f'>= {TRACKED_SHARE_MIN:g}, never lost'
        value = tracking['min_share']
        passed = bool(meeting) and all(meeting)
        points.append(acceptance_point('tracked (c)/(a)', target, value, meeting, passed))
    if movers is not None:
        value = movers['late'] + movers['missed']
        meeting = [m['late'] + m['missed'] == 0 for m in movers['per_seed']]
        target = f'0 late or missed (within {REVOCATION_FRAMES} frames)'
        points.append(acceptance_point('movers revoked', target, value, meeting, value == 0))
    if (b_over_a := ratios.get('b_over_a')) is not None:
        value, seeds = b_over_a['ratio_of_means'], b_over_a['per_seed']
        meeting = [r['ratio'] >= B_OVER_A_MIN or r['diverged'] for r in seeds]
        passed = value >= B_OVER_A_MIN or (bool(seeds) and all(r['diverged'] for r in seeds))
        target = f'>= {B_OVER_A_MIN:g} or diverges'
        points.append(acceptance_point('ATE(b)/ATE(a)', target, value, meeting, passed))
    return points


def acceptance_point(
    name: str, target: str, value: float, meeting: Sequence[bool], passed: bool
) -> dict[str, Any]:
    """Return one point: name, target, value, seeds meeting it ('n/N'), verdict."""
    return {
        'name': name,
        'target': target,
        'value': value,
        'seeds_meeting': f'{sum(meeting)}/{len(meeting)}',
        'passed': bool(passed),
    }


def rms_over_runs(errors: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return per frame the RMS of ``errors`` (runs, frames) over runs with an estimate."""
    finite = np.isfinite(errors)
    counts = np.count_nonzero(finite, axis=0)
    sums = np.sum(np.where(finite, errors, 0.0) ** 2, axis=0)
    return np.where(counts > 0, np.sqrt(sums / np.maximum(counts, 1)), np.nan)


def report(settings: Settings, collected: Collected, wall_s: float) -> dict[str, Any]:
    """Return the JSON report: configuration, variants, curves, ratios, acceptance, failures."""
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
            'ate_rms_m': rms_over_runs(errors),
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
    tracking = None
    if {'a', 'c'} <= set(settings.variants):  # a variant that failed on every seed: []
        tracking = tracking_summary(per_variant.get('c', []), base or [])
    kept_ratios = {k: v for k, v in ratios.items() if v is not None}
    movers = mover_summary(per_variant.get('c', []))
    markers, scene = settings.markers(), settings.scene()
    frames = sum(collected.frames.values())
    filter_s = sum(collected.filter_s.values())
    return {
        'config': {
            'sequence': None if settings.sequence is None else str(settings.sequence),
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
            'start': collected.start,
        },
        'variants': variants,
        'ratios': kept_ratios,
        'ratios_sim3': {k: v for k, v in ratios_sim3.items() if v is not None},
        'tracking_c': tracking,
        'movers_c': movers,
        'acceptance': acceptance(kept_ratios, tracking, movers),
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
    """A table cell: the value with ``digits`` decimals, '--' if missing or not finite."""
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
    """Return the printed summary: variants, Shadow numbers, ratios, PASS/FAIL per point."""
    config = content['config']
    pipeline = config['pipeline']
    classifier = pipeline['shadow']['classifier']
    rule = classifier['unchecked_directions']
    board = config.get('known_board')
    known = f'board {board[0]}x{board[1]}' if board else 'one target'
    source = f'seeds {config["seeds"]}, {config["scene"]["duration_s"]:g} s'
    if config.get('sequence'):
        source, known = f'sequence {config["sequence"]}', "the sequence's"
    if config.get('start') == 'depth':
        known = 'the first frame with depths'
    waits = (
        '; undecided features on probation' if pipeline['slam'].get('undecided_probation') else ''
    ) + ('' if pipeline['slam'].get('second_order', True) else '; first-order inverse depth')
    waits += '; (a) new features on probation' if pipeline['slam'].get('new_probation') else ''
    lines = [
        f'MonoSLAM Fig. 5, {source}; known points: {known}; STATIC rule: {rule} unchecked '
        f'direction(s), static test {classifier["static_test"]}{waits}',
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
                f'{shadow["frames_processed"]}, without a pose {shadow["frames_without_pose"]}, '
                f'pose covariance not finite {shadow["frames_pose_not_finite"]}'
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
    if (movers := content.get('movers_c')) is not None:
        lines.append(
            f'  (c) moving features in the map: {movers["entries"]} entered; revoked or deleted '
            f'within {REVOCATION_FRAMES} frames of moving across the line of sight '
            f'{movers["in_time"]}, late {movers["late"]}, missed {movers["missed"]}; left view '
            f'{movers["left_view"]}; never moved across while in it (radial) '
            f'{movers["radial"]}; removed before moving across {movers["removed_early"]}; '
            f'latency median {number_text(movers["latency_median_frames"], 1)}, max '
            f'{number_text(movers["latency_max_frames"], 0)} frames; '
            f'gone with a loss of tracking {movers["lost_with_map"]}; '
            f'{movers["revoked"]} revocations handed back to the Shadow filter, '
            f'{movers["revoked_static"]} of them of static points'
        )
        seen = movers['observable']
        lines.append(
            f'      judged from motion out of the epipolar plane (what one camera can see): in '
            f'time {seen["in_time"]}, late {seen["late"]}, missed {seen["missed"]}, left view '
            f'{seen["left_view"]}, never moving so {seen["radial"]}, removed before '
            f'{seen["removed_early"]}; latency median '
            f'{number_text(seen["latency_median_frames"], 1)} frames'
        )
    lines += seed_lines(content)
    if content['acceptance']:
        lines.append("  paper 001's claims on these seeds (the means; seeds meeting it alone):")
    for point in content['acceptance']:
        verdict = 'met' if point['passed'] else 'NOT met'
        value = number_text(point['value'], 2)
        lines.append(
            f'  {point["name"]:16s} {value:>8s}  target {point["target"]:30s}'
            f' seeds meeting {point["seeds_meeting"]:6s} {verdict}'
        )
    if (c_over_a := content['ratios'].get('c_over_a')) is not None:
        meeting = sum(r['ratio'] <= C_OVER_A_GOAL for r in c_over_a['per_seed'])
        lines.append(
            f'  (the goal for ATE(c)/ATE(a) is {C_OVER_A_GOAL:g}: '
            f'{number_text(c_over_a["ratio_of_means"], 2)}, seeds meeting it '
            f'{meeting}/{len(c_over_a["per_seed"])})'
        )
    for failure in content['failures']:
        lines.append(
            f'  FAILED RUN seed {failure["seed"]} ({failure["variant"]}): {failure["error"]}'
        )
    return '\n'.join(lines)


def seed_lines(content: Mapping[str, Any]) -> list[str]:
    """Return the per seed table: frames tracked and ATE (m) per variant, (c) against (a)."""
    runs = {
        variant: {run['seed']: run for run in data['per_seed']}
        for variant, data in content['variants'].items()
    }
    tracking = {r['seed']: r for r in (content.get('tracking_c') or {}).get('per_seed', [])}
    variants = list(runs)
    header = (
        ''.join(f'{f"tracked {v}":>11s}' for v in variants)
        + ''.join(f'{f"ATE {v}":>9s}' for v in variants)
        + f'{"c/a frames":>11s}{"c/a ATE":>9s}{"c lost":>8s}{"Shadow f":>10s}{"handed":>8s}'
    )
    lines = [f'  {"seed":>4s}{header}']
    for seed in sorted({seed for by_seed in runs.values() for seed in by_seed}):
        seed_runs = [runs[v].get(seed) for v in variants]
        cells = ''.join(
            f'{run["frames_tracked"] if run else "failed":>11}' for run in seed_runs
        ) + ''.join(f'{number_text(run["ate_m"]) if run else "--":>9s}' for run in seed_runs)
        a_run, c_run = runs.get('a', {}).get(seed), runs.get('c', {}).get(seed)
        share = tracking[seed]['share'] if seed in tracking else None
        ratio = safe_ratio(c_run['ate_m'], a_run['ate_m']) if a_run and c_run else None
        lost = ('yes' if c_run['lost_frames'] else 'no') if c_run else '--'
        shadow = c_run.get('shadow', {}) if c_run else {}
        cells += (
            f'{number_text(share, 3):>11s}{number_text(ratio, 2):>9s}{lost:>8s}'
            f'{shadow.get("frames_processed", "--"):>10}{shadow.get("handovers", "--"):>8}'
        )
        lines.append(f'  {seed:>4d}{cells}')
    return lines
