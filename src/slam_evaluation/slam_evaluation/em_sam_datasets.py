"""em_sam_evaluate's real data sets: --mrclam and --victoria-park, runs and results."""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

from slam_core.datasets import data_root
from slam_core.errors import DatasetError
from slam_core.files import write_atomically, write_json
from slam_evaluation.em_sam_runs import FULL_RUN, parse_window, window_label
from slam_evaluation.plotting import render_png
from slam_sim.core.mrclam import ROBOT_SUBJECTS, robots_with_odometry

VICTORIA_PARK_FILE = 'victoria_park/victoria_park.txt'


def _window(text: str) -> float | None:
    try:
        return parse_window(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def add_dataset_options(parser: argparse.ArgumentParser) -> None:
    """Add --mrclam, --robots, --window-s and --victoria-park to ``parser``."""
    parser.add_argument(
        '--mrclam',
        type=Path,
        metavar='DIR',
        help='an MRCLAM data set directory (e.g. <datasets>/mrclam/MRCLAM_Dataset1)',
    )
    parser.add_argument(
        '--robots',
        type=int,
        nargs='+',
        choices=ROBOT_SUBJECTS,
        metavar='N',
        help='with --mrclam: robots to evaluate (default: every robot with an odometry file)',
    )
    parser.add_argument(
        '--window-s',
        type=_window,
        nargs='+',
        metavar='S',
        help="with --mrclam: time windows, seconds from each robot's first odometry stamp; "
        f"'{FULL_RUN}' or 0 is the whole run (default: {FULL_RUN}), e.g. --window-s full 600 300",
    )
    parser.add_argument(
        '--victoria-park',
        type=Path,
        metavar='FILE_OR_BAG',
        nargs='?',
        const=Path(),
        help='the Victoria Park GTSAM text file, or a bag victoria_park_import made '
        f'(no value: <datasets>/{VICTORIA_PARK_FILE})',
    )


def run_datasets(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """Run --mrclam or --victoria-park, print the report and write it to --output."""
    if args.mrclam is None and (args.robots or args.window_s):
        parser.error('--robots and --window-s go with --mrclam')
    if args.mrclam is not None:
        title, text, content, figures = _mrclam(args)
    else:
        source = args.victoria_park if args.victoria_park != Path() else None
        title, text, content, figures = _victoria_park(source)
    report = f'# {title}\n\n{text}\n'
    if args.output is not None:
        write_atomically(args.output / 'results.md', report)
        write_json(args.output / 'results.json', content)
        if not args.no_figures:
            for name, png in figures().items():
                write_atomically(args.output / name, png)
    print(report)  # noqa: T201
    return 0


def _mrclam(args: argparse.Namespace) -> tuple[str, str, dict[str, Any], Any]:
    from slam_evaluation import em_sam_dataset_figures as figures
    from slam_evaluation.em_sam_mrclam import evaluate_mrclam, markdown

    dataset = args.mrclam
    available = robots_with_odometry(dataset)
    robots = list(dict.fromkeys(args.robots)) if args.robots else list(available)
    missing = [k for k in robots if k not in available]
    if missing:
        raise DatasetError(
            f'{dataset}: no odometry file for robots {missing} '
            f'(Robot{missing[0]}_Odometry.dat); robots with odometry: {list(available)}'
        )
    windows = list(dict.fromkeys(args.window_s)) if args.window_s else [None]
    results = evaluate_mrclam(dataset, robots, windows)
    title = (
        f'EM-SAM on {dataset.name}: robots {robots}, windows {[window_label(w) for w in windows]}'
    )
    content = {
        'dataset': str(dataset),
        'scores': [asdict(s) for r in results for s in r.scores],
        'runs': {r.name: {k: v for k, v in r.extras.items()} for r in results},
    }

    def pngs() -> dict[str, bytes]:
        return {
            f'{r.name}.png': render_png(figures.draw_mrclam_run, r, figures.MRCLAM_SIZE_IN)
            for r in results
        }

    return title, markdown(results), content, pngs


def _victoria_park(source: Path | None) -> tuple[str, str, dict[str, Any], Any]:
    from slam_evaluation import em_sam_dataset_figures as figures
    from slam_evaluation.em_sam_victoria_park import evaluate_victoria_park, markdown, tree_table

    path = source if source is not None else data_root() / VICTORIA_PARK_FILE
    if not path.exists():
        raise DatasetError(f'{path}: no such file or bag (Victoria Park); check the path')
    result = evaluate_victoria_park(path, log=lambda line: print(line, file=sys.stderr))  # noqa: T201
    content = {
        'source': str(path),
        'all_static': {
            'cost': result.all_static.cost,
            'status': result.all_static.status,
            'runtime_s': result.all_static.runtime_s,
        },
        'em_runtime_s': {mode: runtime for mode, (runtime, _) in result.em.items()},
        'trees': tree_table(result),
        'flagged_robust': [
            {
                'tree': t.tree,
                'weight': t.weight,
                'sightings': len(t.sightings_m),
                'median_distance_m': t.median_distance_m,
                'max_distance_m': t.max_distance_m,
                'spread_m': t.spread_m,
            }
            for t in result.flagged
        ],
        'timings_s': result.timings_s,
    }

    def pngs() -> dict[str, bytes]:
        png = render_png(figures.draw_victoria_park, result, figures.victoria_park_size_in(result))
        return {'victoria_park_flagged.png': png}

    return 'EM-SAM on Victoria Park', markdown(result), content, pngs
