"""em_sam_evaluate: score EM-SAM on simulated bags and on the real data sets.

    em_sam_evaluate BAG [BAG ...] [--output DIR]
    em_sam_evaluate --simulate 0-9 [--variant standard] [--output DIR]
    em_sam_evaluate --mrclam DIR [--robots 1 2 ...] [--window-s full 600 300] [--output DIR]
    em_sam_evaluate --victoria-park FILE_OR_BAG [--output DIR]

Simulated runs compare odometry only, plain SAM, EM-SAM 'paper' and 'robust' and an oracle
(movers removed) on ATE and map error (m, SE(2)-aligned), moveable precision/recall and
runtime. Writes results.md, results.json and PNG figures into the output directory.

Design notes: docs/design/evaluation.md
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from em_sam_node.core.assembly import MappingData, dead_reckoning
from em_sam_node.core.em import run_em
from em_sam_node.core.em_types import EmConfig, EmResult
from em_sam_node.mapper.report import write_figures
from em_sam_node.offline import GroundTruth, read_ground_truth, replay_bag, seen_at_both_positions
from slam_core.arrays import FloatArray
from slam_core.cli import PlainDescriptionHelpFormatter, console_main
from slam_core.files import write_atomically, write_json
from slam_core.progress import ProgressReporter
from slam_evaluation.em_sam_datasets import add_dataset_options, run_datasets
from slam_evaluation.em_sam_metrics import align_se2, ate_rmse, classify, landmark_rmse
from slam_evaluation.em_sam_runs import solve_all_static
from slam_sim.core.office import Variant

METHODS = ('odometry', 'plain_sam', 'em_sam_paper', 'em_sam_robust', 'oracle', 'live_mapper')


@dataclass(frozen=True)
class Score:
    """One method on one run."""

    run: str
    method: str
    ate_m: float
    map_error_m: float
    precision: float
    recall: float
    flagged_static: int
    runtime_s: float


@dataclass(frozen=True)
class MethodOutput:
    """A method's trajectory (N,3), static landmark estimates and flagged ids."""

    poses: FloatArray
    landmark_ids: np.ndarray
    positions: FloatArray
    flagged: set[int]
    runtime_s: float
    em: EmResult | None = None
    stamps_ns: np.ndarray | None = None  # keyframe stamps, when not the replayed ones


def run_methods(data: MappingData, truth: GroundTruth) -> dict[str, MethodOutput]:
    """Run the five methods on one run's data."""
    outputs: dict[str, MethodOutput] = {}
    started = time.perf_counter()
    poses = dead_reckoning(data)
    outputs['odometry'] = MethodOutput(
        poses, np.zeros(0, dtype=np.int64), np.zeros((0, 2)), set(), time.perf_counter() - started
    )
    for method, exclude in (
        ('plain_sam', []),
        ('oracle', truth.landmark_ids[truth.moveable].tolist()),
    ):
        # The oracle is robust mode's estimator with the moved landmarks known: it calibrates
        # the odometry as robust mode does.
        calibrate = method == 'oracle' and EmConfig(mode='robust').calibrate_odometry
        solved = solve_all_static(data, exclude, calibrate=calibrate)
        outputs[method] = MethodOutput(
            solved.poses, solved.landmark_ids, solved.positions, set(), solved.runtime_s
        )
    for mode in ('paper', 'robust'):
        started = time.perf_counter()
        result = run_em(data, EmConfig(mode=mode), record_snapshots=False)
        runtime = time.perf_counter() - started
        static = ~result.moveable
        outputs[f'em_sam_{mode}'] = MethodOutput(
            result.poses,
            result.landmark_ids[static],
            result.positions[static],
            set(result.landmark_ids[result.moveable].tolist()),
            runtime,
            result,
        )
    return outputs


def score(
    run: str, data: MappingData, truth: GroundTruth, outputs: dict[str, MethodOutput]
) -> list[Score]:
    """Return the metrics of every method on one run."""
    true_xy = truth.poses_at(data.keyframe_stamps_ns)[:, :2]
    positives = seen_at_both_positions(data, truth)
    negatives = set(truth.landmark_ids[~truth.moveable].tolist())
    static_truth = dict(zip(truth.landmark_ids.tolist(), truth.positions_before, strict=True))
    scores = []
    for method, output in outputs.items():
        truth_xy = true_xy if output.stamps_ns is None else truth.poses_at(output.stamps_ns)[:, :2]
        alignment = align_se2(output.poses[:, :2], truth_xy)
        keep = [i for i, lid in enumerate(output.landmark_ids.tolist()) if lid in negatives]
        map_error = landmark_rmse(
            output.positions[keep],
            np.array([static_truth[int(output.landmark_ids[i])] for i in keep]).reshape(-1, 2),
            alignment,
        )
        counts = classify(output.flagged, positives, negatives)
        em_method = method.startswith('em_sam') or method == 'live_mapper'
        scores.append(
            Score(
                run=run,
                method=method,
                ate_m=ate_rmse(output.poses[:, :2], truth_xy),
                map_error_m=map_error,
                precision=counts.precision if em_method else float('nan'),
                recall=counts.recall if em_method else float('nan'),
                flagged_static=counts.false_positives,
                runtime_s=output.runtime_s,
            )
        )
    return scores


def markdown_table(scores: list[Score]) -> str:
    """Return per-method means over runs as a Markdown table."""
    lines = [
        '| method | runs | ATE RMSE m | map error m | moveable precision | moveable recall '
        '| static flagged (total) | runtime s |',
        '|---|---:|---:|---:|---:|---:|---:|---:|',
    ]
    for method in METHODS:
        mine = [s for s in scores if s.method == method]
        if not mine:
            continue

        def mean(values: list[float]) -> str:
            finite = [v for v in values if np.isfinite(v)]
            return f'{np.mean(finite):.3f}' if finite else '-'

        lines.append(
            f'| {method} | {len(mine)} | {mean([s.ate_m for s in mine])} | '
            f'{mean([s.map_error_m for s in mine])} | {mean([s.precision for s in mine])} | '
            f'{mean([s.recall for s in mine])} | {sum(s.flagged_static for s in mine)} | '
            f'{mean([s.runtime_s for s in mine])} |'
        )
    return '\n'.join(lines)


def evaluate_bag(
    path: Path, output: Path | None, live_report: Path | None = None
) -> tuple[list[Score], dict[str, MethodOutput]]:
    """Replay one bag, run the methods, score them, and write its figures if asked."""
    replay = replay_bag(path)
    truth = read_ground_truth(path)
    outputs = run_methods(replay.data, truth)
    if live_report is not None:
        outputs['live_mapper'] = live_output(live_report)
    if output is not None:
        for mode in ('paper', 'robust'):
            figures = run_em(replay.data, EmConfig(mode=mode), record_snapshots=True)
            write_figures(figures, output / path.stem, prefix=f'em_sam_{mode}')
    return score(path.stem, replay.data, truth, outputs), outputs


def live_output(report_path: Path) -> MethodOutput:
    """Return the em_sam_mapper node's own result (report JSON) at its keyframe stamps."""
    report = json.loads(report_path.read_text(encoding='utf-8'))
    static = [lm for lm in report['landmarks'] if not lm['moveable']]
    return MethodOutput(
        poses=np.array(report['trajectory']['poses'], dtype=float).reshape(-1, 3),
        landmark_ids=np.array([lm['id'] for lm in static], dtype=np.int64),
        positions=np.array([lm['position_m'] for lm in static], dtype=float).reshape(-1, 2),
        flagged=set(report['moveable_ids']),
        runtime_s=float(report['timings_s'].get('total', float('nan'))),
        stamps_ns=np.array(report['trajectory']['stamps_ns'], dtype=np.int64),
    )


def _seed_range(text: str) -> list[int]:
    if '-' in text:
        low, high = text.split('-', 1)
        return list(range(int(low), int(high) + 1))
    return [int(part) for part in text.split(',')]


def _simulated_bags(seeds: list[int], variant: str, directory: Path) -> list[Path]:
    from slam_sim.core.office import simulate_office
    from slam_sim.office_bag import write_office_bag

    paths = []
    for seed in seeds:
        path = directory / f'office_{variant}_seed{seed}'
        write_office_bag(simulate_office(seed, variant), path)
        paths.append(path)
    return paths


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='em_sam_evaluate',
        description=__doc__,
        formatter_class=PlainDescriptionHelpFormatter,
    )
    parser.add_argument('bags', nargs='*', type=Path, help='simulated bags with ground truth')
    parser.add_argument('--simulate', metavar='SEEDS', help="simulate seeds, e.g. '0-9' or '1,4'")
    parser.add_argument(
        '--variant',
        default=Variant.STANDARD.value,
        choices=[v.value for v in Variant],
        help='what the moveable markers of the simulated runs do',
    )
    parser.add_argument('--output', type=Path, help='directory for results and figures')
    parser.add_argument('--no-figures', action='store_true', help='skip the figures')
    parser.add_argument(
        '--live-report',
        type=Path,
        metavar='JSON',
        help="em_sam_mapper's em_sam_report.json for the (first) bag: adds a live_mapper row",
    )
    add_dataset_options(parser)
    return parser


@console_main('em_sam_evaluate')
def main(argv: list[str] | None = None) -> int:
    """Evaluate bags, simulated seeds or a real data set; print the table; write results."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    datasets = [args.mrclam is not None, args.victoria_park is not None]
    if sum(datasets) + bool(args.bags or args.simulate) != 1:
        parser.error('give bags or --simulate SEEDS, or --mrclam DIR, or --victoria-park FILE')
    if any(datasets):
        return run_datasets(parser, args)
    with tempfile.TemporaryDirectory(prefix='em_sam_eval_') as scratch:
        bags = list(args.bags)
        if args.simulate:
            bags += _simulated_bags(_seed_range(args.simulate), args.variant, Path(scratch))
        progress = ProgressReporter(len(bags), label='em_sam_evaluate', unit=' runs', period_s=0.0)
        scores: list[Score] = []
        for index, bag in enumerate(bags):
            figures_dir = None if args.no_figures or args.output is None else args.output
            run_scores, _ = evaluate_bag(
                bag, figures_dir if index == 0 else None, args.live_report if index == 0 else None
            )
            scores += run_scores
            progress.update(index + 1)
        progress.finish()
    table = markdown_table(scores)
    print(table)  # noqa: T201
    if args.output is not None:
        write_atomically(args.output / 'results.md', (table + '\n').encode())
        write_json(args.output / 'results.json', {'scores': [asdict(s) for s in scores]})
    return 0


if __name__ == '__main__':
    sys.exit(main())
