"""Benchmark: EM-SAM online against GTSAM iSAM2 on UTIAS MRCLAM whole runs, one keyframe
per update, side by side in the same run.

    python bench/em_sam_online_mrclam.py [--dataset DIR ...] [--robots 1 2 ...] [--output DIR]

Each robot's whole run is imported with ``mrclam_import``'s writer into a temporary
directory and replayed through ``odometry_ingest``'s keyframing (``offline.replay_bag``),
as em_sam_mapper gets it. Then, one keyframe per update, the two interleaved
(``bench_common.side_by_side``, as in em_sam_online.py):

- reference: GTSAM 4.3 iSAM2 with its default parameters on the same factors, every
  landmark static (``gtsam_inputs.mrclam_graph``): a keyframe's odometry factor and
  sightings, the new pose started from the previous pose's estimate, a landmark from its
  first sighting;
- ours: ``IncrementalEmSam`` with the default EmConfig (``em_sam_online.online``).

Per run: latency per update (mean, median, p95, max, ms) and the ratio of the means; the
cost of each last estimate on the all-static graph; the ATE where Vicon tracks the robot;
ours's moveable set scored as em_sam_evaluate scores it (``mrclam_positives``: static
barcodes flagged, positives missed). Writes ``em_sam_online_mrclam.md`` to ``--output``.
Default: data set 6, every robot with odometry (about 10 min on two cores).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))

from bench_common import run_meta, side_by_side  # noqa: E402
from em_sam_online import online_updates  # noqa: E402
from gtsam_inputs import Graph, mrclam_graph, on_grid  # noqa: E402

from em_sam_node.core.assembly import MappingData  # noqa: E402
from em_sam_node.core.em_types import EmConfig  # noqa: E402
from em_sam_node.core.incremental import IncrementalEmSam  # noqa: E402
from em_sam_node.core.incremental_parts import load_gtsam  # noqa: E402
from em_sam_node.offline import GroundTruth, read_ground_truth, replay_bag  # noqa: E402
from slam_core.blas import single_threaded_blas  # noqa: E402
from slam_core.datasets import data_root  # noqa: E402
from slam_core.files import write_atomically  # noqa: E402
from slam_evaluation.em_sam_metrics import ate_rmse  # noqa: E402
from slam_evaluation.mrclam_positives import mrclam_positives  # noqa: E402
from slam_sim.core.mrclam import robots_with_odometry  # noqa: E402
from slam_sim.mrclam_bag import load_run, write_mrclam_bag  # noqa: E402


def isam2_updates(gtsam: Any, graph: Graph, data: MappingData, solver: Any) -> Iterator[int]:
    """Feed ``solver`` (a gtsam.ISAM2) ``graph``'s factors, one keyframe per ``next``
    (module docstring); yields the keyframe just added."""
    problem = graph.built.problem
    incoming = {int(to): m for m, to in enumerate(data.odometry_to.tolist())}
    rows_of: dict[int, list[int]] = {}
    for k, pose in enumerate(problem.obs_pose.tolist()):
        rows_of.setdefault(pose, []).append(k)
    z = on_grid(problem.obs_z)
    known: set[int] = set()
    for pose in range(problem.num_poses):
        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if pose == 0:
            factors.add(graph.graph.at(0))
            start = graph.values.atPose2(0)
        else:
            m = incoming[pose]
            between = graph.graph.at(1 + m)
            factors.add(between)
            previous = solver.calculateEstimatePose2(int(data.odometry_from[m]))
            start = previous.compose(between.measured())
        values.insert(pose, start)
        for k in rows_of.get(pose, []):
            landmark = int(problem.obs_landmark[k])
            factors.add(graph.graph.at(graph.first_observation + k))
            if landmark not in known:
                known.add(landmark)
                local = gtsam.Point2(z[k, 0] * np.cos(z[k, 1]), z[k, 0] * np.sin(z[k, 1]))
                values.insert(gtsam.symbol('l', landmark), start.transformFrom(local))
        solver.update(factors, values)
        yield pose


def _stats(latencies: list[float]) -> tuple[float, float, float, float]:
    ms = np.asarray(latencies) * 1e3
    return float(ms.mean()), float(np.median(ms)), float(np.percentile(ms, 95)), float(ms.max())


def _ratio(mean: float, reference_mean: float | None) -> str:
    return 'n/a' if reference_mean is None else f'{mean / reference_mean:.2f}'


def _ate(poses: np.ndarray, data: MappingData, truth: GroundTruth) -> str:
    if not truth.has_poses:
        return 'n/a'
    covered = truth.covers(data.keyframe_stamps_ns)
    true_xy = truth.poses_at(data.keyframe_stamps_ns[covered])[:, :2]
    return f'{ate_rmse(poses[covered, :2], true_xy):.3f}'


def bench_run(gtsam: Any, dataset: Path, robot: int) -> list[str]:
    """The rows of one robot's whole run: the reference's and ours."""
    run = load_run(dataset, robot, None)
    scratch = Path(tempfile.mkdtemp())
    try:
        write_mrclam_bag(run, scratch / 'run')
        data = replay_bag(scratch / 'run').data
        truth = read_ground_truth(scratch / 'run')
    finally:
        shutil.rmtree(scratch)
    graph = mrclam_graph(gtsam, data)
    solver = gtsam.ISAM2(gtsam.ISAM2Params())
    smoother = IncrementalEmSam(EmConfig(), data.prior_pose, data.prior_cov)
    (plain, ours), (failure, ours_failure) = side_by_side(
        [
            isam2_updates(gtsam, graph, data, solver),
            online_updates(smoother, data, data.num_keyframes),
        ],
        data.num_keyframes,
    )
    if ours_failure is not None:
        raise RuntimeError(f'ours failed at keyframe {len(ours)}: {ours_failure}')
    reference = None if failure is not None else solver.calculateEstimate()
    ours_values = gtsam.Values()
    poses = smoother.poses()
    for i, pose in enumerate(poses):
        ours_values.insert(i, gtsam.Pose2(*pose))
    positions = smoother.landmark_positions()
    for j, landmark_id in enumerate(graph.built.landmark_ids.tolist()):
        ours_values.insert(gtsam.symbol('l', j), np.asarray(positions[int(landmark_id)]))
    name = f'{dataset.name} robot {robot} ({data.num_keyframes} keyframes)'
    rows = []
    if reference is None:
        rows.append(
            f'| {name} | iSAM2 | failed at keyframe {len(plain)}: {failure} | | | | | | | |'
        )
        reference_mean = float('nan')
    else:
        reference_mean = _stats(plain)[0]
        reference_poses = np.array(
            [[(p := reference.atPose2(i)).x(), p.y(), p.theta()] for i in range(len(poses))]
        )
    statics = set(truth.landmark_ids[~truth.moveable].tolist())
    positives = set(mrclam_positives(run, data, whole_run=True))
    flagged = set(smoother.moveable)
    runs = [
        (
            'ours',
            ours,
            ours_values,
            poses,
            f'{sorted(flagged & statics) or "-"} / {sorted(positives - flagged) or "-"}',
        )
    ]
    if reference is not None:
        runs.insert(0, ('iSAM2', plain, reference, reference_poses, '-'))
    for solver, latencies, values, estimate, flags in runs:
        mean, median, p95, peak = _stats(latencies)
        rows.append(
            f'| {name} | {solver} | {mean:.2f} | {median:.2f} | {p95:.1f} | {peak:.1f} | '
            f'{_ratio(mean, None if reference is None else reference_mean)} | '
            f'{graph.graph.error(values):.1f} | '
            f'{_ate(estimate, data, truth)} | {flags} |'
        )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        '--dataset', type=Path, nargs='+', default=[data_root() / 'mrclam' / 'MRCLAM_Dataset6']
    )
    parser.add_argument('--robots', type=int, nargs='+', choices=(1, 2, 3, 4, 5))
    parser.add_argument('--output', type=Path, default=ROOT / 'bench' / 'results')
    args = parser.parse_args()
    single_threaded_blas()
    gtsam = load_gtsam()
    lines = [
        '# EM-SAM online against iSAM2: MRCLAM whole runs, one keyframe per update',
        '',
        ', '.join(f'{k} {v}' for k, v in run_meta('not pinned').items()),
        '',
        '| run | solver | mean ms | median ms | p95 ms | max ms | mean / iSAM2 | '
        'cost, all-static graph | ATE m | static flagged / positives missed |',
        '|---|---|---|---|---|---|---|---|---|---|',
    ]
    for dataset in args.dataset:
        for robot in args.robots or robots_with_odometry(dataset):
            print(f'em_sam_online_mrclam: {dataset.name} robot {robot} ...', file=sys.stderr)
            lines += bench_run(gtsam, dataset, robot)
    report = '\n'.join(lines) + '\n'
    print(report)
    args.output.mkdir(parents=True, exist_ok=True)
    write_atomically(args.output / 'em_sam_online_mrclam.md', report)
    return 0


if __name__ == '__main__':
    sys.exit(main())
