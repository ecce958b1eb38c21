"""Benchmark: EM-SAM on UTIAS MRCLAM data sets, per robot and time window, against GTSAM.

    bash scripts/bootstrap.sh                  # installs gtsam (requirements/python.txt)
    python bench/mrclam_gtsam.py [--dataset DIR [DIR ...]] [--robots 1 2 3 4 5]
        [--window-s full 600 300] [--gnc-spread N] [--output bench/results]

Each robot's run (default data set 6; every robot with an odometry file unless --robots;
each --window-s: the first S seconds from the robot's first odometry stamp, 'full' or 0 the
whole run) is imported with ``mrclam_import``'s writer (slam_sim.mrclam_bag) into a
temporary directory and replayed through the nodes' processors (``offline.replay_bag``: the
odometry_ingest keyframing and noise model the node uses). Sightings of the other robots
are real moving landmarks (the positives: ``slam_evaluation.mrclam_positives``, those the
Vicon tracks put at two places, or without tracks those a whole run sighted often); the
static barcodes are the negatives. Rows, all from the same keyframed data and the same
dead-reckoning start (landmarks placed from their first sighting):

- odometry only; plain SAM (ours, every landmark static, Levenberg-Marquardt);
- EM-SAM ``paper`` and ``robust`` (``em_sam_node.core.em.run_em``);
- GTSAM 4.3 Levenberg-Marquardt, every landmark static, on the same factors: each
  differential-drive increment as a BetweenFactor<Pose2> (exact mean, first-order
  covariance), each sighting as a BearingRangeFactor2D with the same noise, the same prior;
- GTSAM 4.3 GNC with the truncated least squares loss (GncLMOptimizer, odometry and prior
  known inliers, GTSAM's default inlier threshold: the 0.99 chi-square quantile) on the
  same factors; a landmark counts as flagged when most of its sightings end with GNC
  weight below 0.5;
- the oracle: plain SAM (ours) with the other robots removed.

Both GTSAM rows use Levenberg-Marquardt with Marquardt's diagonal damping
(``setDiagonalDamping``), GTSAM's defaults otherwise: with the default lambda I damping,
LM stops on these graphs once lambda passes its 1e5 bound after ~10 iterations, far from
converged (robot 1, full run: cost 72801 against 69848), and GNC's weights were computed
from those unconverged solves. Every number handed to GTSAM is rounded to a fixed grid
(``gtsam_inputs``) so that last-bit differences in our float pipeline cannot change GNC's
discrete inlier decisions: GNC-TLS is bistable on some runs (bench/README.md).
``--gnc-spread N`` reruns GNC on N copies of the odometry scaled by 1 + 1e-8 e (e standard
normal, seeded; far below the data's resolution) and reports the range of its ATE.

ATE is the RMSE after an SE(2) alignment over the keyframes Vicon covers, only where
``RobotN_Groundtruth.dat`` exists (data set 6); without it the ATE columns say n/a. Writes
mrclam_gtsam.md (a section per data set, a table per robot and window, the acceptance
checks of EM-SAM robust: no static barcode flagged, every positive flagged, ATE no worse
than GNC's where there is truth; and one cross-data-set table to paste into
bench/README.md), mrclam_gtsam.json and mrclam_gtsam.png (trajectories), atomically.
Exit status 1 if a check fails.
"""

from __future__ import annotations

import argparse
import importlib
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from bench_common import source_revision
from gtsam_inputs import mrclam_graph, poses_of

from em_sam_node.core.assembly import MappingData, dead_reckoning
from em_sam_node.offline import GroundTruth, read_ground_truth, replay_bag
from slam_core.datasets import data_root
from slam_core.errors import SlamError
from slam_core.files import write_atomically, write_json
from slam_evaluation.em_sam_metrics import ate_rmse
from slam_evaluation.em_sam_runs import (
    flagged_ids,
    parse_window,
    run_em_modes,
    solve_all_static,
    timed,
    window_label,
)
from slam_evaluation.mrclam_positives import (
    MIN_PLACE_SIGHTINGS,
    MIN_SEPARATION_M,
    MIN_SIGHTINGS,
    mrclam_positives,
)
from slam_sim.core.mrclam import robots_with_odometry
from slam_sim.mrclam_bag import load_run, write_mrclam_bag

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATASET = 'mrclam/MRCLAM_Dataset6'
GNC_OUTLIER_WEIGHT = 0.5  # a sighting whose final GNC weight is below this is an outlier
# --gnc-spread's relative odometry perturbation: ~5e-9 m on a 0.5 m keyframe increment, far
# below the data's millimetre resolution and above the 2^-30 (9.3e-10) grid of GTSAM's inputs.
SPREAD_SCALE = 1e-8
FIGURE_COLUMNS = 5
CROSS_METHODS = ('EM-SAM robust', 'EM-SAM paper', 'GTSAM LM', 'GTSAM GNC-TLS')


@dataclass
class Row:
    """One method on one run: ATE (NaN without truth), flagged ids, wall time, poses."""

    method: str
    ate_m: float
    flagged: set[int] | None
    seconds: float
    poses: np.ndarray = field(repr=False)
    note: str = ''


@dataclass
class RunRows:
    """The rows of one robot and window, and what the report needs about the run."""

    dataset: str
    robot: int
    window: str
    positives: set[int]
    negatives: set[int]
    has_truth: bool
    rows: list[Row]
    truth_poses: np.ndarray = field(repr=False)


def lm_params(gtsam: Any) -> Any:
    """GTSAM's LM parameters with Marquardt's diagonal damping (see the module docstring)."""
    params = gtsam.LevenbergMarquardtParams()
    params.setDiagonalDamping(True)
    return params


def gtsam_lm(gtsam: Any, data: MappingData) -> tuple[np.ndarray, str]:
    """Plain GTSAM LM, every landmark static; the poses and its cost and iterations."""
    graph = mrclam_graph(gtsam, data)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph.graph, graph.values, lm_params(gtsam))
    result = optimizer.optimize()
    note = f'cost {graph.graph.error(result):.6g}, {optimizer.iterations()} iterations'
    return poses_of(result, graph.built.problem.num_poses), note


def gnc_tls(gtsam: Any, data: MappingData) -> tuple[np.ndarray, set[int]]:
    """GTSAM GNC-TLS on the same factors; returns the poses and the flagged landmark ids."""
    graph = mrclam_graph(gtsam, data)
    params = gtsam.GncLMParams(lm_params(gtsam))
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers(list(range(graph.first_observation)))
    optimizer = gtsam.GncLMOptimizer(graph.graph, graph.values, params)
    result = optimizer.optimize()
    weights = np.asarray(optimizer.getWeights())[graph.first_observation :]
    problem = graph.built.problem
    flagged = set()
    for j, landmark_id in enumerate(graph.built.landmark_ids.tolist()):
        mine = weights[problem.obs_landmark == j]
        if mine.size and np.mean(mine < GNC_OUTLIER_WEIGHT) > 0.5:
            flagged.add(int(landmark_id))
    return poses_of(result, problem.num_poses), flagged


def gnc_spread(gtsam: Any, data: MappingData, ate: Any, copies: int) -> str:
    """Return the range of GNC's ATE over ``copies`` perturbed copies of the odometry."""
    values = []
    for seed in range(copies):
        noise = np.random.default_rng(seed).standard_normal(data.odometry_u.shape)
        perturbed = replace(data, odometry_u=data.odometry_u * (1.0 + SPREAD_SCALE * noise))
        values.append(ate(gnc_tls(gtsam, perturbed)[0]))
    return f'ATE over {copies} perturbed copies: {min(values):.4f} to {max(values):.4f} m'


def evaluate(
    gtsam: Any, data: MappingData, truth: GroundTruth, spread: int
) -> tuple[list[Row], np.ndarray]:
    """The rows of one replayed run, and the Vicon poses (empty without)."""
    covered = truth.covers(data.keyframe_stamps_ns)
    has_truth = np.count_nonzero(covered) >= 2
    true_xy = truth.poses_at(data.keyframe_stamps_ns[covered])[:, :2] if has_truth else None

    def ate(poses: np.ndarray) -> float:
        return ate_rmse(poses[covered, :2], true_xy) if true_xy is not None else float('nan')

    odometry = dead_reckoning(data)
    rows = [Row('odometry only', ate(odometry), None, 0.0, odometry)]
    static = solve_all_static(data)
    rows.append(
        Row(
            'plain SAM (ours, all static)', ate(static.poses), None, static.runtime_s, static.poses
        )
    )
    for mode, (seconds, result) in run_em_modes(data).items():
        rows.append(
            Row(f'EM-SAM {mode}', ate(result.poses), flagged_ids(result), seconds, result.poses)
        )
    seconds, (poses, note) = timed(lambda: gtsam_lm(gtsam, data))
    rows.append(Row('GTSAM LM', ate(poses), None, seconds, poses, note))
    seconds, (poses, flagged) = timed(lambda: gnc_tls(gtsam, data))
    note = gnc_spread(gtsam, data, ate, spread) if spread and has_truth else ''
    rows.append(Row('GTSAM GNC-TLS', ate(poses), flagged, seconds, poses, note))
    robots = truth.landmark_ids[truth.moveable].tolist()
    oracle = solve_all_static(data, robots)
    rows.append(
        Row(
            'oracle (other robots removed)',
            ate(oracle.poses),
            None,
            oracle.runtime_s,
            oracle.poses,
        )
    )
    return rows, truth.poses if truth.has_poses else np.zeros((0, 3))


def run_rows(
    gtsam: Any, dataset: Path, robot: int, window_s: float | None, scratch: Path, spread: int
) -> RunRows:
    """Import one robot's window, replay it and evaluate every method."""
    run = load_run(dataset, robot, window_s)
    bag = scratch / f'{dataset.name}_robot{robot}_{window_label(window_s).replace(" ", "")}'
    write_mrclam_bag(run, bag)
    data = replay_bag(bag).data
    truth = read_ground_truth(bag)
    shutil.rmtree(bag)  # a full run's bag is ~8 MB; keep one at a time
    rows, truth_poses = evaluate(gtsam, data, truth, spread)
    return RunRows(
        dataset=dataset.name,
        robot=robot,
        window=window_label(window_s),
        positives=set(mrclam_positives(run, data, whole_run=window_s is None)),
        negatives=set(truth.landmark_ids[~truth.moveable].tolist()),
        has_truth=bool(np.isfinite(rows[0].ate_m)),
        rows=rows,
        truth_poses=truth_poses,
    )


def _ids(values: set[int]) -> str:
    return ', '.join(str(v) for v in sorted(values)) if values else '-'


def run_table(run: RunRows) -> list[str]:
    """Return the Markdown table of one robot and window."""
    ate_head, ate_rule = (' ATE m |', '---:|') if run.has_truth else ('', '')
    lines = [
        f'### {run.dataset} robot {run.robot}, {run.window}',
        '',
        f'|method |{ate_head} robots flagged | robots missed | static flagged | time s | note |',
        f'|---|{ate_rule}---:|---|---|---:|---|',
    ]
    for row in run.rows:
        ate = f' {row.ate_m:.4f} |' if run.has_truth else ''
        if row.flagged is None:
            flags = '- | - | -'
        else:
            hits = len(row.flagged & run.positives)
            flags = (
                f'{hits} / {len(run.positives)} | {_ids(run.positives - row.flagged)} | '
                f'{_ids(row.flagged & run.negatives)}'
            )
        lines.append(f'| {row.method} |{ate} {flags} | {row.seconds:.2f} | {row.note} |')
    if not run.has_truth:
        lines += ['', 'No RobotN_Groundtruth.dat for this robot: no ATE.']
    return [*lines, '']


def checks(run: RunRows) -> list[tuple[str, bool]]:
    """Return the acceptance checks of EM-SAM robust on one run."""
    robust = next(r for r in run.rows if r.method == 'EM-SAM robust')
    gnc = next(r for r in run.rows if r.method == 'GTSAM GNC-TLS')
    flagged = robust.flagged or set()
    name = f'{run.dataset} robot {run.robot} {run.window}'
    result = [
        (f'{name}: no static barcode flagged', not (flagged & run.negatives)),
        (
            f'{name}: every positive flagged',
            run.positives <= flagged,
        ),
    ]
    if run.has_truth:
        result.append(
            (
                f'{name}: ATE no worse than GNC ({robust.ate_m:.4f} vs {gnc.ate_m:.4f} m)',
                robust.ate_m <= gnc.ate_m,
            )
        )
    return result


def cross_table(runs: list[RunRows]) -> list[str]:
    """Return one table over data sets, robots and windows, to paste into bench/README.md:
    per method, robots flagged / positives; static false positives; robots missed; ATE
    where there is truth; time."""
    head = ' | '.join(f'{m}: flags; static FP; missed; ATE m; s' for m in CROSS_METHODS)
    lines = [f'| data set | robot | window | {head} |', '|---|---:|---|' + '---|' * 4]
    for run in runs:
        cells = []
        for method in CROSS_METHODS:
            row = next(r for r in run.rows if r.method == method)
            ate = f'{row.ate_m:.3f}' if run.has_truth else 'n/a'
            if row.flagged is None:
                cells.append(f'-; -; -; {ate}; {row.seconds:.1f}')
                continue
            hits = len(row.flagged & run.positives)
            missed = ' '.join(str(k) for k in sorted(run.positives - row.flagged)) or '-'
            cells.append(
                f'{hits}/{len(run.positives)}; {len(row.flagged & run.negatives)}; {missed}; '
                f'{ate}; {row.seconds:.1f}'
            )
        lines.append(f'| {run.dataset} | {run.robot} | {run.window} | {" | ".join(cells)} |')
    return lines


def draw(figure: Any, runs: list[RunRows]) -> None:
    """One panel per run: EM-SAM robust and GNC-TLS trajectories (unaligned), Vicon."""
    columns = min(len(runs), FIGURE_COLUMNS)
    axes = np.atleast_1d(figure.subplots(-(-len(runs) // columns), columns)).ravel()
    for ax, run in zip(axes, runs, strict=False):
        if len(run.truth_poses):
            ax.plot(*run.truth_poses[:, :2].T, color='0.6', lw=0.6, label='Vicon')
        for row in run.rows:
            if row.method in ('EM-SAM robust', 'GTSAM GNC-TLS'):
                ax.plot(*row.poses[:, :2].T, lw=0.7, label=row.method)
        ax.set_title(f'{run.dataset} robot {run.robot} {run.window}', fontsize=8)
        ax.set_aspect('equal')
        ax.legend(fontsize=6)
    for ax in axes[len(runs) :]:
        ax.set_axis_off()


def run_json(run: RunRows) -> dict[str, Any]:
    """Return a run's rows as JSON-ready values (ids sorted, no poses)."""

    def ids(values: set[int] | None) -> list[int] | None:
        return None if values is None else sorted(values)

    return {
        'dataset': run.dataset,
        'robot': run.robot,
        'window': run.window,
        'positives': ids(run.positives),
        'negatives': ids(run.negatives),
        'has_truth': run.has_truth,
        'rows': [
            {
                'method': row.method,
                'ate_m': row.ate_m,
                'flagged': ids(row.flagged),
                'seconds': row.seconds,
                'note': row.note,
            }
            for row in run.rows
        ],
    }


def _windows(parser: argparse.ArgumentParser, values: list[str]) -> list[float | None]:
    try:
        return list(dict.fromkeys(parse_window(v) for v in values))
    except ValueError as err:
        parser.error(f'--window-s: {err}')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        '--dataset',
        type=Path,
        nargs='+',
        default=None,
        help=f'MRCLAM data set directories (default: <datasets>/{DEFAULT_DATASET})',
    )
    parser.add_argument('--robots', type=int, nargs='+', choices=(1, 2, 3, 4, 5))
    parser.add_argument('--window-s', nargs='+', default=['full'], metavar='S')
    parser.add_argument('--gnc-spread', type=int, default=0, metavar='N')
    parser.add_argument('--output', type=Path, default=ROOT / 'bench' / 'results')
    args = parser.parse_args()
    windows = _windows(parser, args.window_s)
    try:
        gtsam: Any = importlib.import_module('gtsam')
    except ImportError:
        print('mrclam_gtsam: gtsam is not installed: run bash scripts/bootstrap.sh')
        return 2
    datasets = args.dataset or [data_root() / DEFAULT_DATASET]
    names = ', '.join(d.name for d in datasets)
    lines = [
        f'# MRCLAM ({names}): EM-SAM per robot and window against GTSAM LM and GNC-TLS',
        '',
        f'Revision {source_revision()}. ATE after SE(2) alignment over the Vicon-covered '
        f'keyframes (data sets with RobotN_Groundtruth.dat only); positives: the other robots '
        f'the Vicon tracks put at two places more than {MIN_SEPARATION_M} m apart with '
        f'{MIN_PLACE_SIGHTINGS} sightings each, or without tracks those a whole run sighted '
        f'at least {MIN_SIGHTINGS} times; static: the barcodes 6-20.',
        '',
    ]
    runs: list[RunRows] = []
    sections: list[str] = []
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as directory:
        for dataset in datasets:
            available = robots_with_odometry(dataset)
            robots = [r for r in (args.robots or available) if r in available]
            sections += [f'## {dataset.name}', '']
            for robot in robots:
                for window_s in windows:
                    run = run_rows(
                        gtsam, dataset, robot, window_s, Path(directory), args.gnc_spread
                    )
                    runs.append(run)
                    sections += run_table(run)
                    write_reports(args.output, [*lines, *sections], runs)  # after every run
                    print(
                        f'mrclam_gtsam: {dataset.name} robot {robot} {run.window} done '
                        f'({len(runs)} runs, {time.perf_counter() - started:.0f} s)',
                        file=sys.stderr,
                        flush=True,
                    )
    report, passed = write_reports(args.output, [*lines, *sections], runs)
    from slam_evaluation.plotting import render_png

    columns = min(len(runs), FIGURE_COLUMNS)
    png = render_png(draw, runs, (4.0 * columns, 4.0 * -(-len(runs) // columns)))
    write_atomically(args.output / 'mrclam_gtsam.png', png)
    print(report)
    return 0 if passed else 1


def write_reports(output: Path, lines: list[str], runs: list[RunRows]) -> tuple[str, bool]:
    """Write mrclam_gtsam.md and .json of the runs so far; return the report and whether
    every check passed."""
    results = [check for run in runs for check in checks(run)]
    lines = [*lines, '## Acceptance (EM-SAM robust)', '']
    lines += [f'- {name}: **{"PASS" if ok else "FAIL"}**' for name, ok in results]
    lines += ['', '## All runs (for bench/README.md)', '', *cross_table(runs), '']
    report = '\n'.join(lines)
    write_atomically(output / 'mrclam_gtsam.md', report)
    write_json(
        output / 'mrclam_gtsam.json',
        {'revision': source_revision(), 'runs': [run_json(run) for run in runs]},
    )
    return report, all(ok for _, ok in results)


if __name__ == '__main__':
    try:
        sys.exit(main())
    except SlamError as err:  # a missing data set or file, a malformed line: named, no traceback
        print(f'mrclam_gtsam: error: {err}', file=sys.stderr)
        sys.exit(2)
