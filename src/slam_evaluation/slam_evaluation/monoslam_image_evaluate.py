"""monoslam_image_evaluate: Fig. 5 from rendered images or bags, against the measurement level.

Design notes: docs/design/evaluation.md
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from slam_core.blas import single_threaded_blas
from slam_core.cli import console_main
from slam_core.errors import BagError
from slam_core.files import write_atomically, write_json
from slam_core.progress import ProgressReporter
from slam_evaluation.evaluation_cli import parse_seeds

if TYPE_CHECKING:
    from slam_evaluation.monoslam_image_runs import Settings

PROG = 'monoslam_image_evaluate'

REPORT_NAME = 'monoslam_image_eval.json'
TABLE_NAME = 'monoslam_image_eval.md'


# --- command line ---------------------------------------------------------------------------


def _arguments(argv: list[str] | None) -> Settings:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument(
        '--out',
        type=Path,
        default=Path('out/monoslam_image_eval'),
        help='output directory (default out/monoslam_image_eval)',
    )
    parser.add_argument('--seeds', help='seeds to render, e.g. 0-9 (default) or 1,4')
    parser.add_argument('--duration-s', type=float, help='rendered run length, s (default 20)')
    parser.add_argument(
        '--bag',
        type=Path,
        nargs='+',
        action='extend',
        default=[],
        help='dynamic_camera_sim bags to evaluate instead of rendering (one run each)',
    )
    parser.add_argument(
        '--unchecked-directions',
        type=int,
        default=1,
        choices=(0, 1, 2),
        help="the Shadow filter's STATIC rule as monoslam_evaluate (default 1)",
    )
    parser.add_argument(
        '--target-every-n-frames',
        type=int,
        default=1,
        help="search the target in every n-th image only (marker_detector's "
        'detect_every_n_frames; default 1)',
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    # the pipeline (OpenCV, the renderer, the filters): imported once --help is out of the way
    from slam_evaluation import monoslam_runs
    from slam_evaluation.monoslam_image_runs import Settings
    from slam_evaluation.monoslam_image_sources import bag_source, rendered_source
    from slam_evaluation.monoslam_pipeline import VARIANTS

    if args.target_every_n_frames < 1:
        parser.error(f'--target-every-n-frames {args.target_every_n_frames}: must be >= 1')
    if args.bag and (args.seeds is not None or args.duration_s is not None):
        parser.error('--bag: a bag brings its own seed and duration; drop --seeds/--duration-s')
    try:
        seeds = parse_seeds(args.seeds or '0-9')
    except ValueError as error:
        parser.error(str(error))
    duration_s = args.duration_s if args.duration_s is not None else 20.0
    evaluation = monoslam_runs.Settings(
        seeds, duration_s, VARIANTS, args.out, args.unchecked_directions
    )
    try:
        scene = evaluation.scene()
    except ValueError as error:
        parser.error(f'--duration-s {duration_s:g}: {error}')
    sources = [rendered_source(seed, scene) for seed in seeds]
    if args.bag:
        missing = [str(path) for path in args.bag if not path.exists()]
        if missing:
            parser.error(f'--bag: {", ".join(missing)}: no such file or directory')
        try:
            sources = [bag_source(path) for path in args.bag]
        except BagError as error:
            parser.error(f'--bag: {error}')
    return Settings(tuple(sources), evaluation, args.out, args.target_every_n_frames)


@console_main(PROG)
def main(argv: list[str] | None = None) -> int:
    """Run the evaluation, print the table, write report, table, figures; 1 if a filter raised."""
    settings = _arguments(argv)
    from slam_evaluation.monoslam_image_figures import write_figures
    from slam_evaluation.monoslam_image_report import report, table_text
    from slam_evaluation.monoslam_image_runs import evaluate_source, seed_line

    single_threaded_blas()
    started = time.perf_counter()
    total = sum(source.frame_count for source in settings.sources)
    progress = ProgressReporter(total, label=PROG, unit=' images')
    results, done = [], 0

    def advance() -> None:
        nonlocal done
        done += 1
        progress.update(done)

    for source in settings.sources:
        results.append(evaluate_source(source, settings, advance))
        print(f'{PROG}: {seed_line(results[-1])}', file=sys.stderr)  # noqa: T201
    progress.finish()
    content = report(settings, results, time.perf_counter() - started)
    figures = write_figures(settings.out, results, content['curves']['rate_hz'])
    content['figures'] = [path.name for path in figures]
    content['runtime']['wall_s'] = time.perf_counter() - started
    write_json(settings.out / REPORT_NAME, content)
    table = table_text(content)
    write_atomically(settings.out / TABLE_NAME, table + '\n')
    print(table)  # noqa: T201
    print(f'wrote {settings.out / REPORT_NAME}, {TABLE_NAME} and {len(figures)} figures')  # noqa: T201
    return 1 if content['failures'] else 0


if __name__ == '__main__':
    sys.exit(main())
