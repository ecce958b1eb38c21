"""monoslam_loop_evaluate: MonoSLAM's persistent map on a loop (measurement level or images).

Design notes: docs/design/evaluation.md
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.blas import single_threaded_blas
from slam_core.cli import console_main
from slam_core.files import write_atomically, write_json
from slam_core.progress import ProgressReporter
from slam_evaluation.evaluation_cli import parse_seeds
from slam_evaluation.monoslam_loop import (
    LOOP_AWAY_S,
    LOOP_DURATION_S,
    LoopRun,
    loop_frames,
    loop_scene,
    map_history,
    position_errors,
    run_loop,
)
from slam_evaluation.monoslam_pipeline import PipelineError
from slam_evaluation.monoslam_runs import Settings
from slam_evaluation.plotting import render_png

REPORT_NAME = 'monoslam_loop.json'
MIN_REMATCHED = 0.8
MIN_REMATCHED_IMAGES = 0.6
MAX_DUPLICATES = 0.05
LOOP_VARIANTS = ('a', 'c')
SCENES = {'with': True, 'without': False}


def _choices(text: str, allowed: tuple[str, ...], flag: str) -> tuple[str, ...]:
    parts = tuple(dict.fromkeys(part.strip() for part in text.split(',') if part.strip()))
    if not parts or any(part not in allowed for part in parts):
        raise ValueError(f'{flag} {text!r}: use a comma list of {", ".join(allowed)}')
    return parts


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog='monoslam_loop_evaluate', description=__doc__.splitlines()[0]
    )
    parser.add_argument('--out', type=Path, default=Path('out/monoslam_loop'))
    parser.add_argument('--seeds', default='0-9', help='seeds, e.g. 0-9 (default) or 1,4')
    parser.add_argument('--variants', default=','.join(LOOP_VARIANTS), help='a, c or a,c')
    parser.add_argument('--movers', default='with,without', help='with, without or both')
    parser.add_argument('--away-s', type=float, default=LOOP_AWAY_S, help='time turned away')
    parser.add_argument('--duration-s', type=float, default=LOOP_DURATION_S)
    parser.add_argument(
        '--images', action='store_true', help='render the images and run closed loop on them'
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        args.seeds = parse_seeds(args.seeds)
        args.variants = _choices(args.variants, LOOP_VARIANTS, '--variants')
        args.movers = _choices(args.movers, tuple(SCENES), '--movers')
        if not math.isfinite(args.away_s) or args.away_s <= 0.0:
            raise ValueError(f'--away-s {args.away_s}: must be > 0 s')
        settings = Settings(args.seeds, args.duration_s, args.variants, args.out)
        loop_scene(settings, True, args.away_s)  # validates the durations
    except ValueError as error:
        parser.error(str(error))
    return args


def acceptance(runs: list[dict[str, Any]], target: float = MIN_REMATCHED) -> dict[str, Any]:
    """Return the acceptance of one variant and scene over its seeds (``target``: re-matched)."""
    returned = sum(run['returned'] for run in runs)
    rematched = sum(run['rematched'] for run in runs)
    share = rematched / returned if returned else math.nan
    points = {
        'rematched': {'value': share, 'pass': bool(share >= target), 'target': target},
        'duplicates': {
            'value': max(run['duplicate_share'] for run in runs),
            'pass': all(run['duplicate_share'] < MAX_DUPLICATES for run in runs),
        },
        'closed': {
            'value': sum(run['closed'] for run in runs),
            'pass': all(run['closed'] for run in runs),
        },
        'never_lost': {
            'value': sum(not run['lost'] for run in runs),
            'pass': not any(run['lost'] for run in runs),
        },
    }
    wrong = sum(run.get('wrong', 0) for run in runs)
    return {
        'seeds': len(runs), 'returned': returned, 'rematched': rematched, 'wrong': wrong,
        'points': points,
    }  # fmt: skip


def summary_text(content: dict[str, Any]) -> str:
    """Return the printed summary: per run, then PASS or FAIL per point."""
    lines = [
        f'MonoSLAM loop ({content["level"]} level), seeds {content["seeds"]}, '
        f'{content["duration_s"]:g} s, turned away {content["away_s"]:g} s',
        '  variant movers seed  mapped back rematched  dup  far max m  last 1 s m  closed  lost',
    ]
    for key, group in content['groups'].items():
        variant, movers = key.split('/')
        for run in group['runs']:
            lines.append(
                f'  ({variant})     {movers:7s} {run["seed"]:4d} {run["mapped_before_turn"]:6d} '
                f'{run["returned"]:4d} {run["rematched"]:9d} {run["duplicates"]:4d} '
                f'{run["far_side_max_m"]:10.3f} {run["last_second_rms_m"]:11.3f} '
                f'{"yes" if run["closed"] else "NO":>7s} {"YES" if run["lost"] else "no":>5s}'
            )
    for key, group in content['groups'].items():
        points = group['acceptance']['points']
        verdict = ' '.join(
            f'{name} {"met" if point["pass"] else "NOT met"}' for name, point in points.items()
        )
        share = points['rematched']['value']
        wrong = group['acceptance']['wrong']
        lines.append(
            f'  ({key}): re-matched {group["acceptance"]["rematched"]}/'
            f'{group["acceptance"]["returned"]} = {share:.1%} (target >= '
            f'{points["rematched"]["target"]:.0%}{f"; {wrong} wrong" if wrong else ""}); '
            f'closed {points["closed"]["value"]}/{group["acceptance"]["seeds"]}, never lost '
            f'{points["never_lost"]["value"]}/{group["acceptance"]["seeds"]}: {verdict}'
        )
    return '\n'.join(lines)


def _draw_map(figure: Any, run: LoopRun) -> None:
    history = map_history(run.record, run.scene.rate_hz)
    times = np.arange(len(history['state'])) / run.scene.rate_hz
    axes = figure.add_subplot(1, 1, 1)
    for name in ('state', 'measured', 'searched', 'rematched', 'deleted', 'evicted'):
        axes.plot(times, history[name], label=name)
    _mark_loop(axes, run)
    axes.set_xlabel('time, s')
    axes.set_ylabel('features')
    axes.set_title(f'map features, seed {run.seed}, ({run.variant}), {_movers(run)}')
    axes.legend(loc='upper left', fontsize=8)


def _draw_error(figure: Any, run: LoopRun) -> None:
    errors = position_errors(run.record, run.frames)
    times = np.arange(len(errors)) / run.scene.rate_hz
    axes = figure.add_subplot(1, 1, 1)
    axes.plot(times, errors, label='camera position error')
    _mark_loop(axes, run)
    first = run.metrics['first_rematch_frame']
    if first is not None:
        axes.axvline(first / run.scene.rate_hz, color='green', label='first re-match')
    axes.set_xlabel('time, s')
    axes.set_ylabel('error, m')
    axes.set_title(f'position error, seed {run.seed}, ({run.variant}), {_movers(run)}')
    axes.legend(loc='upper left', fontsize=8)


def _movers(run: LoopRun) -> str:
    return 'with movers' if run.movers else 'without movers'


def _mark_loop(axes: Any, run: LoopRun) -> None:
    marks = loop_frames(run.scene)
    rate = run.scene.rate_hz
    axes.axvspan(marks['start'] / rate, marks['away'] / rate, color='0.9', label='turning')
    axes.axvspan(marks['return'] / rate, marks['back'] / rate, color='0.9')
    axes.axvspan(marks['away'] / rate, marks['return'] / rate, color='0.97', label='far side')


@console_main('monoslam_loop_evaluate')
def main(argv: list[str] | None = None) -> int:
    """Run the loop evaluation; print the summary; write the report and figures."""
    args = _arguments(argv)
    # the image pipeline (OpenCV, the renderer): imported once --help is out of the way
    from slam_evaluation.monoslam_image_sources import rendered_source
    from slam_evaluation.monoslam_loop_images import run_image_loop

    single_threaded_blas()
    started = time.perf_counter()
    settings = Settings(args.seeds, args.duration_s, args.variants, args.out)
    jobs = [(v, m, s) for m in args.movers for s in args.seeds for v in args.variants]
    frames_per_run = loop_scene(settings, True, args.away_s).frame_count
    renders = len(args.movers) * len(args.seeds) if args.images else 0
    progress = ProgressReporter((len(jobs) + renders) * frames_per_run,
                                label='monoslam_loop_evaluate', unit=' frames')  # fmt: skip
    done = 0

    def advance() -> None:
        nonlocal done
        done += 1
        progress.update(done)

    groups: dict[str, dict[str, Any]] = {}
    failures: list[dict[str, Any]] = []
    figures: list[str] = []
    rendered: tuple[tuple[str, int], Any] | None = None
    for variant, movers, seed in jobs:
        key = f'{variant}/{movers}'
        try:
            if args.images:
                if rendered is None or rendered[0] != (movers, seed):
                    scene = loop_scene(settings, SCENES[movers], args.away_s)
                    source = rendered_source(seed, scene)
                    images = []
                    for image in source.frames():
                        images.append(image)
                        advance()
                    rendered = ((movers, seed), (source, images))
                source, images = rendered[1]
                run = run_image_loop(settings, source, images, variant, SCENES[movers], advance)
            else:
                run = run_loop(settings, seed, SCENES[movers], variant, args.away_s)
        except PipelineError as error:
            failures.append({'seed': seed, 'variant': variant, 'movers': movers,
                             'error': str(error)})  # fmt: skip
            traceback.print_exception(error, file=sys.stderr)
            continue
        finally:
            if not args.images:  # images advance one by one
                done += frames_per_run
                progress.update(done)
        groups.setdefault(key, {'runs': []})['runs'].append({'seed': seed, **run.metrics})
        if len(groups[key]['runs']) == 1:
            args.out.mkdir(parents=True, exist_ok=True)
            for name, draw in (('map', _draw_map), ('error', _draw_error)):
                path = args.out / f'loop_{name}_{variant}_{movers}.png'
                write_atomically(path, render_png(draw, run, (8.0, 4.0)))
                figures.append(path.name)
    progress.finish()
    target = MIN_REMATCHED_IMAGES if args.images else MIN_REMATCHED
    for group in groups.values():
        group['acceptance'] = acceptance(group['runs'], target)
    content = {
        'level': 'image' if args.images else 'measurement',
        'seeds': list(args.seeds),
        'duration_s': args.duration_s,
        'away_s': args.away_s,
        'groups': groups,
        'failures': failures,
        'figures': figures,
        'wall_s': time.perf_counter() - started,
    }
    write_json(args.out / REPORT_NAME, content)
    print(summary_text(content))  # noqa: T201
    print(f'wrote {args.out / REPORT_NAME} and {len(figures)} figures')  # noqa: T201
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())
