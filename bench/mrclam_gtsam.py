"""Benchmark: EM-SAM on UTIAS MRCLAM dataset 6, each robot, against GTSAM GNC-TLS.

    pip install -r requirements/bench.txt      # gtsam, a benchmark-only dependency
    python bench/mrclam_gtsam.py [--robots 1 2 3 4 5] [--output bench/results]

Each robot's run is imported with ``mrclam_import`` (slam_sim.mrclam_bag; into a
temporary directory) and replayed through the nodes' processors (``offline.replay_bag``:
the odometry_ingest keyframing and noise model the node uses). Sightings of the other four
robots are real moving landmarks (the positives); the 15 static barcodes are the
negatives. Rows, all from the same keyframed data and the same dead-reckoning start:

- odometry only;
- plain SAM (every landmark static, Levenberg-Marquardt);
- EM-SAM ``paper`` and ``robust`` (``em_sam_node.core.em.run_em``);
- GTSAM 4.3 GNC with the truncated least squares loss (GncLMOptimizer, odometry and prior
  known inliers) on the same factors: each differential-drive increment as a
  BetweenFactor<Pose2> (exact mean, first-order covariance), each sighting as a
  BearingRangeFactor2D with the same noise; a landmark counts as flagged when most of its
  sightings end with GNC weight below 0.5;
- the oracle: plain SAM with the other robots removed (ground truth).

ATE is the RMSE after an SE(2) alignment, over the keyframes Vicon covers (robot 1's Vicon
track ends about 128 s before its odometry). Writes mrclam_gtsam.md with a table per robot
and the acceptance checks (robust mode: no static barcode flagged; every other robot seen
at least 20 times flagged; ATE no worse than GNC's), and mrclam_gtsam.png (trajectories).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from bench_common import source_revision

from em_sam_node.core.assembly import (
    MappingData,
    build_problem,
    dead_reckoning,
    initial_estimate,
)
from em_sam_node.core.em import run_em
from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.solver import solve
from em_sam_node.offline import read_ground_truth, replay_bag
from slam_evaluation.em_sam_metrics import ate_rmse
from slam_sim import mrclam_bag

ROOT = Path(__file__).resolve().parents[1]
ROBOT_IDS = (1, 2, 3, 4, 5)
MIN_SIGHTINGS = 20


@dataclass(frozen=True)
class Row:
    """One method on one robot."""

    method: str
    ate_m: float
    flagged: set[int]
    seconds: float
    poses: np.ndarray


def between_of_increment(u: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The SE(2) relative pose of a differential-drive increment and its covariance."""
    half = u[:, 2] / 2.0
    c, s = np.cos(half), np.sin(half)
    between = np.column_stack([c * u[:, 0] - s * u[:, 1], s * u[:, 0] + c * u[:, 1], u[:, 2]])
    jacobian = np.zeros((len(u), 3, 3))
    jacobian[:, 0, 0], jacobian[:, 0, 1] = c, -s
    jacobian[:, 1, 0], jacobian[:, 1, 1] = s, c
    jacobian[:, 0, 2] = -0.5 * between[:, 1]
    jacobian[:, 1, 2] = 0.5 * between[:, 0]
    jacobian[:, 2, 2] = 1.0
    return between, jacobian @ cov @ np.swapaxes(jacobian, 1, 2)


def gnc_tls(gtsam: Any, data: MappingData) -> tuple[np.ndarray, set[int]]:
    """GTSAM GNC-TLS on the same factors; returns the poses and the flagged landmark ids."""
    built = build_problem(data)
    problem = built.problem
    start = initial_estimate(problem, dead_reckoning(data))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(
        gtsam.PriorFactorPose2(
            0, gtsam.Pose2(*data.prior_pose), gtsam.noiseModel.Gaussian.Covariance(data.prior_cov)
        )
    )
    between, cov = between_of_increment(data.odometry_u, data.odometry_cov)
    for m in range(len(between)):
        graph.add(
            gtsam.BetweenFactorPose2(
                int(data.odometry_from[m]),
                int(data.odometry_to[m]),
                gtsam.Pose2(*between[m]),
                gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov[m] + cov[m].T)),
            )
        )
    known_inliers = list(range(graph.size()))
    obs_cov = data.obs_cov[built.observation_rows]
    first_observation = graph.size()
    for k in range(problem.num_observations):
        sigma_r, sigma_b = np.sqrt(obs_cov[k, 0, 0]), np.sqrt(obs_cov[k, 1, 1])
        graph.add(
            gtsam.BearingRangeFactor2D(
                int(problem.obs_pose[k]),
                gtsam.symbol('l', int(problem.obs_landmark[k])),
                gtsam.Rot2(float(problem.obs_z[k, 1])),
                float(problem.obs_z[k, 0]),
                gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_b, sigma_r])),
            )
        )
    values = gtsam.Values()
    for i, pose in enumerate(start.poses):
        values.insert(i, gtsam.Pose2(*pose))
    for j, point in enumerate(start.landmarks):
        values.insert(gtsam.symbol('l', j), np.asarray(point, dtype=float))
    params = gtsam.GncLMParams()
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers(known_inliers)
    optimizer = gtsam.GncLMOptimizer(graph, values, params)
    result = optimizer.optimize()
    weights = np.asarray(optimizer.getWeights())[first_observation:]
    poses = np.array(
        [[(p := result.atPose2(i)).x(), p.y(), p.theta()] for i in range(problem.num_poses)]
    )
    flagged = set()
    for j, landmark_id in enumerate(built.landmark_ids.tolist()):
        mine = weights[problem.obs_landmark == j]
        if mine.size and np.mean(mine < 0.5) > 0.5:
            flagged.add(int(landmark_id))
    return poses, flagged


def plain_sam(data: MappingData, exclude: list[int]) -> np.ndarray:
    built = build_problem(data, exclude_ids=exclude)
    result = solve(
        built.problem,
        initial_estimate(built.problem, dead_reckoning(data)),
        method='levenberg_marquardt',
        max_iterations=200,
        relative_cost_tolerance=1e-6,
    )
    return result.estimate.poses


def timed(function: Any) -> tuple[float, Any]:
    started = time.perf_counter()
    value = function()
    return time.perf_counter() - started, value


def evaluate_robot(
    gtsam: Any, bag: Path, robot: int
) -> tuple[list[Row], dict[int, int], np.ndarray]:
    """The rows of one robot, its sightings per landmark id, and its Vicon poses."""
    data = replay_bag(bag).data
    truth = read_ground_truth(bag)
    covered = (data.keyframe_stamps_ns >= truth.stamps_ns[0]) & (
        data.keyframe_stamps_ns <= truth.stamps_ns[-1]
    )
    true_xy = truth.poses_at(data.keyframe_stamps_ns)[:, :2]
    robots = [r for r in ROBOT_IDS if r != robot]

    def ate(poses: np.ndarray) -> float:
        return ate_rmse(poses[covered, :2], true_xy[covered])

    rows = [Row('odometry only', ate(dead_reckoning(data)), set(), 0.0, dead_reckoning(data))]
    seconds, poses = timed(lambda: plain_sam(data, []))
    rows.append(Row('plain SAM (all static)', ate(poses), set(), seconds, poses))
    for mode in ('paper', 'robust'):
        seconds, result = timed(
            lambda mode=mode: run_em(data, EmConfig(mode=mode), record_snapshots=False)
        )
        flagged = {int(i) for i in np.asarray(result.landmark_ids)[result.moveable]}
        rows.append(Row(f'EM-SAM {mode}', ate(result.poses), flagged, seconds, result.poses))
    seconds, (poses, flagged) = timed(lambda: gnc_tls(gtsam, data))
    rows.append(Row('GTSAM 4.3 GNC-TLS', ate(poses), flagged, seconds, poses))
    seconds, poses = timed(lambda: plain_sam(data, robots))
    rows.append(Row('oracle (other robots removed)', ate(poses), set(), seconds, poses))
    ids, counts = np.unique(data.obs_landmark_id, return_counts=True)
    return rows, dict(zip(ids.tolist(), counts.tolist(), strict=True)), truth.poses


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--robots', type=int, nargs='+', default=list(ROBOT_IDS))
    parser.add_argument('--output', type=Path, default=ROOT / 'bench' / 'results')
    args = parser.parse_args()
    try:
        gtsam: Any = importlib.import_module('gtsam')
    except ImportError:
        print('mrclam_gtsam: gtsam is not installed: pip install -r requirements/bench.txt')
        return 2
    lines = [
        '# MRCLAM dataset 6: EM-SAM per robot against GTSAM GNC-TLS',
        '',
        f'Revision {source_revision()}. ATE after SE(2) alignment over the Vicon-covered '
        'keyframes; positives: the other robots (all seen >= 20 times unless noted).',
        '',
    ]
    checks: list[tuple[str, bool]] = []
    figures: list[tuple[int, list[Row], np.ndarray]] = []
    with tempfile.TemporaryDirectory() as directory:
        for robot in args.robots:
            bag = Path(directory) / f'robot{robot}'
            mrclam_bag.main(['--robot', str(robot), '--output', str(bag)])
            rows, counts, truth_poses = evaluate_robot(gtsam, bag, robot)
            positives = {r for r in ROBOT_IDS if r != robot and counts.get(r, 0) >= MIN_SIGHTINGS}
            negatives = {i for i in counts if i > max(ROBOT_IDS)}
            lines += [
                f'## Robot {robot}',
                '',
                '| method | ATE m | robots flagged | static flagged | runtime s |',
                '|---|---:|---:|---:|---:|',
            ]
            for row in rows:
                robots_hit = len(row.flagged & positives)
                lines.append(
                    f'| {row.method} | {row.ate_m:.3f} | {robots_hit} / {len(positives)} | '
                    f'{len(row.flagged & negatives)} | {row.seconds:.2f} |'
                )
            robust = next(r for r in rows if r.method == 'EM-SAM robust')
            gnc = next(r for r in rows if r.method.startswith('GTSAM'))
            checks += [
                (f'robot {robot}: no static barcode flagged', not (robust.flagged & negatives)),
                (
                    f'robot {robot}: every other robot seen >= 20 times flagged',
                    positives <= robust.flagged,
                ),
                (
                    f'robot {robot}: ATE no worse than GNC '
                    f'({robust.ate_m:.4f} vs {gnc.ate_m:.4f} m)',
                    robust.ate_m <= gnc.ate_m,
                ),
            ]
            lines.append('')
            figures.append((robot, rows, truth_poses))
            print(f'robot {robot} done', flush=True)
    lines += ['## Acceptance (EM-SAM robust)', '']
    lines += [f'- {name}: **{"PASS" if ok else "FAIL"}**' for name, ok in checks]
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / 'mrclam_gtsam.md').write_text('\n'.join(lines) + '\n', encoding='utf-8')
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(
        1, len(figures), figsize=(4 * len(figures), 4), layout='constrained'
    )
    for ax, (robot, rows, truth_poses) in zip(np.atleast_1d(axes), figures, strict=True):
        ax.plot(truth_poses[:, 0], truth_poses[:, 1], color='0.6', lw=0.6, label='Vicon')
        for row in rows:
            if row.method in ('EM-SAM robust', 'GTSAM 4.3 GNC-TLS'):
                ax.plot(row.poses[:, 0], row.poses[:, 1], lw=0.7, label=row.method)
        ax.set_title(f'robot {robot} (unaligned)', fontsize=9)
        ax.set_aspect('equal')
        ax.legend(fontsize=6)
    figure.savefig(args.output / 'mrclam_gtsam.png', dpi=110)
    print('\n'.join(lines))
    return 0 if all(ok for _, ok in checks) else 1


if __name__ == '__main__':
    sys.exit(main())
