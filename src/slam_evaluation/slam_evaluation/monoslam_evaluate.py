"""monoslam_evaluate: paper 001's Fig. 5, MonoSLAM with and without the Shadow filter.

Design notes: docs/design/evaluation.md
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from monoslam_shadow_node.shadow_filter.core.shadow_classifier import (
    STATIC_TESTS,
    ClassifierConfig,
)
from slam_core.blas import single_threaded_blas
from slam_core.cli import console_main
from slam_core.files import write_json
from slam_core.progress import ProgressReporter
from slam_evaluation.evaluation_cli import add_tracking_noise_arguments, parse_seeds
from slam_evaluation.monoslam_figures import write_figures
from slam_evaluation.monoslam_pipeline import (
    SHADOW_POSES,
    VARIANTS,
)
from slam_evaluation.monoslam_report import report, summary_text
from slam_evaluation.monoslam_runs import (
    BOARD_GAP_M,
    BOARD_MARKER_SIDE_M,
    Collected,
    Settings,
    evaluate_seed,
    evaluate_sequence,
)
from slam_evaluation.sequence_files import SequenceError, read_sequence
from slam_sim.core.dynamic_config import DynamicSceneConfig

REPORT_NAME = 'monoslam_eval.json'


# --- command line ---------------------------------------------------------------------------


def parse_variants(text: str) -> tuple[str, ...]:
    """Return variants from 'a,b,c' (order kept, duplicates dropped); ValueError if unknown."""
    parts = tuple(dict.fromkeys(part.strip() for part in text.split(',') if part.strip()))
    if not parts or any(part not in VARIANTS for part in parts):
        raise ValueError(f'--variants {text!r}: use a comma list of {", ".join(VARIANTS)}')
    return parts


def parse_board(text: str) -> tuple[int, int]:
    """Return (rows, columns) from 'RxC', both >= 1; ValueError naming the text otherwise."""
    parts = text.lower().split('x')
    if len(parts) == 2 and all(part.strip().isdigit() for part in parts):
        rows, columns = (int(part) for part in parts)
        if rows >= 1 and columns >= 1:
            return rows, columns
    raise ValueError(f'--known-board {text!r}: use rows x columns, both >= 1, e.g. 3x3')


def _arguments(argv: list[str] | None) -> Settings:
    parser = argparse.ArgumentParser(prog='monoslam_evaluate', description=__doc__.splitlines()[0])
    parser.add_argument(
        '--out',
        type=Path,
        default=Path('out/monoslam_eval'),
        help='output directory (default out/monoslam_eval)',
    )
    parser.add_argument('--seeds', default='0-9', help='seeds, e.g. 0-9 (default) or 1,4')
    parser.add_argument(
        '--duration-s',
        type=float,
        default=DynamicSceneConfig().duration_s,
        help='run length, s (default %(default)s)',
    )
    parser.add_argument(
        '--variants', default=','.join(VARIANTS), help='variants to run, e.g. a,c (default a,b,c)'
    )
    parser.add_argument(
        '--unchecked-directions',
        type=int,
        default=1,
        choices=(0, 1, 2),
        help="the Shadow filter's STATIC rule: directions of motion left unchecked "
        '(0: strict, no moving feature handed over in the strict runs; default 1)',
    )
    parser.add_argument(
        '--static-test',
        choices=STATIC_TESTS,
        default=ClassifierConfig().static_test,
        help="the Shadow filter's STATIC tests: both, three_ray (the three-ray test alone) "
        'or all_view (the all-view score test alone); default %(default)s',
    )
    parser.add_argument(
        '--known-board',
        default=None,
        metavar='RxC',
        help=f'known points from a board of R x C markers of {BOARD_MARKER_SIDE_M:g} m, '
        f'{BOARD_GAP_M:g} m apart, instead of the single target (e.g. 3x3)',
    )
    parser.add_argument(
        '--shadow-poses',
        choices=SHADOW_POSES,
        default='slam',
        help="the Shadow filter's camera poses: SLAM's (default) or the truth (a diagnostic "
        'bound: known poses)',
    )
    parser.add_argument(
        '--oracle-handovers',
        action='store_true',
        help='drop handovers of truly moving features (a diagnostic bound)',
    )
    parser.add_argument(
        '--undecided-probation',
        action='store_true',
        help="(c): features the Shadow filter has not decided on fill SLAM's map on probation "
        '(consider updates: they never move the camera) until it clears them',
    )
    parser.add_argument(
        '--new-probation',
        action='store_true',
        help='(a): a new feature corrects only itself (consider updates) until its inverse '
        'depth is linear, as a handover does in (c): (a) is then (c) with a perfect classifier',
    )
    parser.add_argument(
        '--first-order',
        action='store_true',
        help="MonoSLAM without an inverse-depth feature's second-order term (the product of its "
        "inverse depth's and its baseline's uncertainties) in its innovation covariance",
    )
    add_tracking_noise_arguments(parser)
    parser.add_argument(
        '--undeclared',
        action='store_true',
        help='simulate the tracking noise but tell the filters nothing of it (they keep white '
        '1 px): noise a user could not declare',
    )
    parser.add_argument(
        '--sequence',
        type=Path,
        default=None,
        metavar='DIR',
        help='run an on-disk sequence (camera.yaml, poses.txt, tracks.csv, optional '
        'labels.csv, known_points.csv, depths.csv: see the README) instead of simulated seeds',
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        seeds = parse_seeds(args.seeds)
        variants = parse_variants(args.variants)
        board = None if args.known_board is None else parse_board(args.known_board)
    except ValueError as error:
        parser.error(str(error))
    if args.sequence is not None:
        seeds = (0,)
        if board is not None:
            parser.error('--known-board: a sequence brings its own known points')
    settings = Settings(
        seeds,
        args.duration_s,
        variants,
        args.out,
        args.unchecked_directions,
        args.static_test,
        board,
        args.shadow_poses,
        args.oracle_handovers,
        args.sequence,
        args.tracking_offset_px,
        args.tracking_jump_probability,
        args.undecided_probation,
        not args.undeclared,
        not args.first_order,
        args.new_probation,
    )
    try:
        settings.scene()
    except ValueError as error:
        parser.error(str(error))
    return settings


@console_main('monoslam_evaluate')
def main(argv: list[str] | None = None) -> int:
    """Run the evaluation, print the summary, write report and figures; 1 if a filter raised."""
    settings = _arguments(argv)
    single_threaded_blas()
    started = time.perf_counter()
    sequence = None
    frames = settings.scene().frame_count
    if settings.sequence is not None:
        try:
            sequence = read_sequence(settings.sequence)
        except SequenceError as error:
            print(f'monoslam_evaluate: error: --sequence: {error}', file=sys.stderr)  # noqa: T201
            return 2
        if 'a' in settings.variants and sequence.labels is None:
            print(  # noqa: T201
                'monoslam_evaluate: error: --sequence: variant a needs labels.csv (it runs on '
                'the static features only); use --variants b,c',
                file=sys.stderr,
            )
            return 2
        frames = len(sequence.stamps_ns)
    total = len(settings.seeds) * len(settings.variants) * frames
    progress = ProgressReporter(total, label='monoslam_evaluate', unit=' frames')
    collected, done = Collected(), 0

    def advance(count: int) -> None:
        nonlocal done
        done += count
        progress.update(done)

    if sequence is not None:
        evaluate_sequence(settings, sequence, collected, advance)
    for seed in settings.seeds if sequence is None else ():
        evaluate_seed(settings, seed, collected, advance)
    progress.finish()
    content = report(settings, collected, time.perf_counter() - started)
    figures = write_figures(settings.out, content, collected)
    content['figures'] = [path.name for path in figures]
    content['runtime']['wall_s'] = time.perf_counter() - started
    write_json(settings.out / REPORT_NAME, content)
    print(summary_text(content))  # noqa: T201
    print(f'wrote {settings.out / REPORT_NAME} and {len(figures)} figures')  # noqa: T201
    return 1 if collected.failures else 0


if __name__ == '__main__':
    sys.exit(main())
