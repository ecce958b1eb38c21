"""shadow_evaluate: the Shadow filter on simulated runs, scored like paper 001's Figs. 2-4.

Design notes: docs/design/evaluation.md
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

from monoslam_shadow_node.shadow_filter.core.shadow_classifier import (
    STATIC_TESTS,
    ClassifierConfig,
)
from slam_core.cli import console_main
from slam_core.files import write_json
from slam_core.progress import ProgressReporter
from slam_evaluation.evaluation_cli import add_tracking_noise_arguments, parse_seeds
from slam_evaluation.sequence_files import SequenceError, read_sequence
from slam_evaluation.shadow_experiments import (
    Collected,
    Settings,
    classify_seed,
    consistency_seed,
    figure_inputs,
    report,
)
from slam_evaluation.shadow_report import summary_text, write_figures
from slam_evaluation.shadow_runs import FilterRunError
from slam_evaluation.shadow_sequence import evaluate_sequence, sequence_summary
from slam_sim.core.dynamic_config import DynamicSceneConfig

QUICK_DURATION_S = 4.0


def _parse_alphas(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(part) for part in text.split(',') if part.strip())
    except ValueError as error:
        raise argparse.ArgumentTypeError(f'--alphas {text!r}: use e.g. 0.01,0.05,0.1') from error


def _arguments(argv: list[str] | None) -> Settings:
    parser = argparse.ArgumentParser(prog='shadow_evaluate', description=__doc__.splitlines()[0])
    parser.add_argument(
        '--seeds', type=parse_seeds, help='seeds, e.g. 0-9 (default, the acceptance seeds) or 1,4'
    )
    parser.add_argument(
        '--consistency-seeds',
        type=parse_seeds,
        help='seeds of the model-motion runs (default: --seeds)',
    )
    parser.add_argument(
        '--out',
        type=Path,
        default=Path('out/shadow_eval'),
        help='output directory (default out/shadow_eval)',
    )
    parser.add_argument('--duration-s', type=float, help='run length, s (default 20)')
    parser.add_argument(
        '--alpha',
        type=float,
        default=ClassifierConfig().alpha,
        help='classifier significance level (default %(default)s)',
    )
    parser.add_argument(
        '--alphas',
        type=_parse_alphas,
        help='alpha sweep, e.g. 0.01,0.05,0.1 (default; --alpha is added)',
    )
    parser.add_argument(
        '--focal-px',
        type=float,
        default=DynamicSceneConfig().focal_px,
        help='focal length, px (default %(default)s)',
    )
    parser.add_argument(
        '--window-frames',
        type=int,
        default=30,
        help="decision window and 'parallax allows' span (default 30)",
    )
    parser.add_argument(
        '--consistency-objects',
        type=int,
        default=12,
        help='model-motion objects per consistency run (default 12)',
    )
    parser.add_argument(
        '--unchecked-directions',
        type=int,
        default=ClassifierConfig().unchecked_directions,
        help='directions of motion the STATIC rule may leave unchecked: 0 (strict: no moving '
        'feature handed over, slow), 1 (default) or 2',
    )
    parser.add_argument(
        '--static-test',
        choices=STATIC_TESTS,
        default=ClassifierConfig().static_test,
        help='the STATIC tests: both, three_ray (the three-ray test alone) or all_view (the '
        'all-view score test alone); default %(default)s',
    )
    add_tracking_noise_arguments(parser)
    parser.add_argument(
        '--sequence',
        type=Path,
        default=None,
        metavar='DIR',
        help='run the filter over an on-disk sequence (known poses; see the README) instead '
        'of the simulated runs',
    )
    parser.add_argument(
        '--quick',
        action='store_true',
        help=f'smoke run: seed 0, {QUICK_DURATION_S:g} s, no alpha sweep',
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    seeds = args.seeds or ((0,) if args.quick else tuple(range(10)))
    if args.alphas is None:
        args.alphas = () if args.quick else (0.01, 0.05, 0.1)
    if args.window_frames < 1 or args.consistency_objects < 1:
        parser.error('--window-frames and --consistency-objects must be at least 1')
    duration = args.duration_s or (
        QUICK_DURATION_S if args.quick else DynamicSceneConfig().duration_s
    )
    try:
        settings = Settings(
            seeds,
            args.consistency_seeds or seeds,
            args.alpha,
            tuple(sorted({args.alpha, *args.alphas})),
            duration,
            args.focal_px,
            args.window_frames,
            args.consistency_objects,
            args.out,
            args.unchecked_directions,
            args.static_test,
            args.sequence,
            args.tracking_offset_px,
            args.tracking_jump_probability,
        )
        (
            settings.scene(),
            settings.shadow(args.alpha),
            [settings.shadow(a) for a in settings.alphas],
        )
    except ValueError as error:
        parser.error(str(error))
    return settings


@console_main('shadow_evaluate')
def main(argv: list[str] | None = None) -> int:
    """Run the evaluation, print the summary, write report and figures; 1 if the filter raised."""
    settings = _arguments(argv)
    if settings.sequence is not None:
        return _run_sequence(settings)
    started = time.perf_counter()
    total = len(settings.seeds) * len(settings.alphas) + len(settings.consistency_seeds)
    progress = ProgressReporter(total, label='shadow_evaluate', unit=' runs', period_s=0.0)
    collected, done = Collected(), 0
    for seed in settings.seeds:
        done += classify_seed(settings, seed, collected)
        progress.update(done)
    for seed in settings.consistency_seeds:
        done += consistency_seed(settings, seed, collected)
        progress.update(done)
    progress.finish()
    content = report(settings, collected, time.perf_counter() - started)
    figures = write_figures(settings.out, figure_inputs(settings, collected, content))
    content['figures'] = [path.name for path in figures]
    content['runtime']['wall_s'] = time.perf_counter() - started
    write_json(settings.out / 'shadow_eval.json', content)
    print(summary_text(content))  # noqa: T201
    print(f'wrote {settings.out / "shadow_eval.json"} and {len(figures)} figures')  # noqa: T201
    return 1 if collected.failures else 0


def _run_sequence(settings: Settings) -> int:
    """``--sequence``: the filter over an on-disk sequence (``shadow_sequence``)."""
    assert settings.sequence is not None
    try:
        sequence = read_sequence(settings.sequence)
    except SequenceError as error:
        print(f'shadow_evaluate: error: --sequence: {error}', file=sys.stderr)  # noqa: T201
        return 2
    try:
        config = settings.shadow(settings.alpha)
        if sequence.tracker is not None:
            config = dataclasses.replace(config, ekf=sequence.tracker.ekf(config.ekf))
        content = evaluate_sequence(sequence, config, str(settings.sequence))
    except FilterRunError as error:
        print(f'shadow_evaluate: the filter failed: {error}', file=sys.stderr)  # noqa: T201
        return 1
    write_json(settings.out / 'shadow_eval_sequence.json', content)
    print(sequence_summary(content))  # noqa: T201
    print(f'wrote {settings.out / "shadow_eval_sequence.json"}')  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
