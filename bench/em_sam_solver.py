"""Benchmark: the EM-SAM sparse solver per Gauss-Newton iteration, next to a dense QR reference.

Problems are random walks (1 m steps, heading noise) with landmarks scattered along the path,
about one landmark per 10 poses, each pose seeing its 2 nearest landmarks at 1 m or more
(about 2 observations per pose). Measurements are noisy; the start is dead reckoning from the
noisy odometry, landmarks placed from their first sighting. Everything is seeded.

Measured in the same run:

* ours: ``em_sam_node.core.solver.solve`` (Gauss-Newton, sparse normal equations, SuperLU
  in symmetric mode with a cached minimum-degree ordering), from the start to convergence.
  Time per iteration = solve time / iterations (factorizations); each iteration linearizes,
  assembles, factorizes, solves and evaluates the cost of the step (and of any halvings).
  The median over ``repeats`` solves is reported, with the problem's layout already cached;
  the first solve of a problem (layout + ordering included) is reported separately.
* reference: one dense iteration as in the paper: the same linearization
  (``build_linear_system``), the whitened Jacobian made dense, a Householder QR of [J | r]
  (LAPACK through ``scipy.linalg.qr``), back-substitution and the cost of the step. It runs
  only up to ``--dense-max-poses`` poses: the QR costs O(m n^2) time and O(m n) memory.
  On the 50-pose problem the dense GN also runs to convergence, to check that both reach the
  same estimate.

Also an "EM pattern" line: 10 Levenberg-Marquardt solves of a 2k-pose problem, the first from
dead reckoning, the next 9 warm-started with random per-landmark row scales, as the EM loop
calls the solver.

The Markdown report goes to ``--output`` and a log-log plot of time per iteration against the
number of poses to ``--plot``. Acceptance: at most 5 ms per Gauss-Newton iteration on the
paper's 50-pose / 100-measurement problem; PASS or FAIL is printed and FAIL exits with 1.

Run (after ``bash scripts/bootstrap.sh``)::

    source scripts/env.sh
    python bench/em_sam_solver.py [--sizes 1000 2000 ...] [--dense-max-poses 2000]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy
import scipy.linalg
from bench_common import source_revision
from scipy.spatial import cKDTree

from em_sam_node.core.factors import range_bearing_predict
from em_sam_node.core.linear_system import build_linear_system, system_layout
from em_sam_node.core.problem import Estimate, SlamProblem, SolveResult
from em_sam_node.core.solver import solve
from slam_core.geometry.se2 import range_bearing_to_point, wrap_angle

BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / 'results' / 'em_sam_solver.md'
DEFAULT_PLOT = BENCH_DIR / 'results' / 'em_sam_solver_scaling.png'
DEFAULT_SIZES = (1000, 2000, 5000, 10000, 20000, 50000)
PAPER_POSES = 50  # with 100 measurements: the paper's ~1 s per dense iteration
ACCEPT_MS_PER_ITERATION = 5.0
ODOMETRY_SIGMA = np.array([0.01, 0.005, 0.002])  # forward m, side m, turn rad per step
OBS_SIGMA = np.array([0.05, 0.01])  # range m, bearing rad
MIN_RANGE_M = 1.0
MAX_ITERATIONS = 100


@dataclass(frozen=True)
class BenchProblem:
    """A seeded problem, its dead-reckoning start and its ground truth."""

    problem: SlamProblem
    initial: Estimate
    truth: Estimate


def _integrate(start: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Return the poses (N+1, 3) reached by chaining eq. 2 increments u (N, 3) from start."""
    headings = start[2] + np.concatenate([[0.0], np.cumsum(u[:, 2])])
    midpoint = headings[:-1] + 0.5 * u[:, 2]
    steps = np.column_stack(
        [
            u[:, 0] * np.cos(midpoint) - u[:, 1] * np.sin(midpoint),
            u[:, 0] * np.sin(midpoint) + u[:, 1] * np.cos(midpoint),
        ]
    )
    positions = start[:2] + np.vstack([np.zeros(2), np.cumsum(steps, axis=0)])
    return np.column_stack([positions, wrap_angle(headings)])


def random_walk_problem(
    num_poses: int, *, seed: int = 0, obs_per_pose: int = 2, poses_per_landmark: int = 10
) -> BenchProblem:
    """Return a random-walk SLAM problem with ~num_poses/10 landmarks, ~2 sightings per pose."""
    rng = np.random.default_rng(seed)
    moves = num_poses - 1
    u_true = np.column_stack([np.full(moves, 0.5), np.zeros(moves), rng.normal(0, 0.2, moves)])
    poses = _integrate(np.zeros(3), u_true)
    num_landmarks = max(1, num_poses // poses_per_landmark)
    anchors = rng.choice(num_poses, num_landmarks, replace=False)
    landmarks = poses[anchors, :2] + rng.normal(0.0, 1.5, (num_landmarks, 2))
    distance, nearest = cKDTree(landmarks).query(poses[:, :2], k=min(num_landmarks, 8))
    distance, nearest = distance.reshape(num_poses, -1), nearest.reshape(num_poses, -1)
    far_enough = distance >= MIN_RANGE_M
    take = far_enough & (np.cumsum(far_enough, axis=1) <= obs_per_pose)
    obs_pose = np.nonzero(take)[0]
    seen, obs_landmark = np.unique(nearest[take], return_inverse=True)
    landmarks = landmarks[seen]
    count = obs_pose.size
    z = range_bearing_predict(poses[obs_pose], landmarks[obs_landmark])
    z += rng.normal(0.0, 1.0, z.shape) * OBS_SIGMA
    z[:, 1] = wrap_angle(z[:, 1])
    u = u_true + rng.normal(0.0, 1.0, u_true.shape) * ODOMETRY_SIGMA
    problem = SlamProblem(
        num_poses=num_poses,
        num_landmarks=len(landmarks),
        odometry_from=np.arange(moves),
        odometry_to=np.arange(1, num_poses),
        odometry_u=u,
        odometry_sqrt_info=np.repeat(np.diag(1.0 / ODOMETRY_SIGMA)[None], moves, axis=0),
        obs_pose=obs_pose.astype(np.int64),
        obs_landmark=obs_landmark.astype(np.int64),
        obs_z=z,
        obs_sqrt_info=np.repeat(np.diag(1.0 / OBS_SIGMA)[None], count, axis=0),
        prior_mean=poses[0].copy(),
        prior_sqrt_info=np.diag([1e3, 1e3, 1e3]),
    )
    dead_reckoning = _integrate(poses[0], u)
    first = np.full(len(landmarks), count)
    np.minimum.at(first, obs_landmark, np.arange(count))
    initial_landmarks = range_bearing_to_point(dead_reckoning[obs_pose[first]], z[first])
    return BenchProblem(
        problem, Estimate(dead_reckoning, initial_landmarks), Estimate(poses, landmarks)
    )


@dataclass(frozen=True)
class OursTiming:
    """Our solver on one problem: medians over repeats, and the first (cold) solve."""

    ms_per_iteration: float
    linearize_ms_per_iteration: float
    factorize_ms_per_iteration: float
    iterations: int
    status: str
    first_solve_ms: float
    lm_iterations: int
    lm_status: str
    result: SolveResult


def time_ours(bench: BenchProblem, repeats: int, *, with_lm: bool) -> OursTiming:
    """Return the Gauss-Newton timing of our sparse solver on the problem."""
    started = time.perf_counter()
    first = solve(bench.problem, bench.initial, max_iterations=MAX_ITERATIONS)
    first_ms = 1e3 * (time.perf_counter() - started)
    totals, linearize, factorize = [], [], []
    result = first
    for _ in range(repeats):
        result = solve(bench.problem, bench.initial, max_iterations=MAX_ITERATIONS)
        iterations = max(1, result.iterations)
        totals.append(result.extra['total_time_s'] / iterations)
        linearize.append(result.extra['linearize_time_s'] / iterations)
        factorize.append(result.extra['factorize_time_s'] / iterations)
    lm_iterations, lm_status = 0, 'not run'
    if with_lm:
        lm = solve(
            bench.problem,
            bench.initial,
            method='levenberg_marquardt',
            max_iterations=MAX_ITERATIONS,
        )
        lm_iterations, lm_status = lm.iterations, lm.status
    return OursTiming(
        ms_per_iteration=1e3 * statistics.median(totals),
        linearize_ms_per_iteration=1e3 * statistics.median(linearize),
        factorize_ms_per_iteration=1e3 * statistics.median(factorize),
        iterations=result.iterations,
        status=result.status,
        first_solve_ms=first_ms,
        lm_iterations=lm_iterations,
        lm_status=lm_status,
        result=result,
    )


def dense_step(problem: SlamProblem, estimate: Estimate) -> np.ndarray:
    """Return the Gauss-Newton step from a Householder QR of the dense [J | r] (reference)."""
    residual, jacobian = build_linear_system(problem, estimate)
    augmented = np.column_stack([jacobian.toarray(), residual])
    upper = scipy.linalg.qr(augmented, mode='r', overwrite_a=True, check_finite=False)[0]
    n = jacobian.shape[1]
    return -scipy.linalg.solve_triangular(upper[:n, :n], upper[:n, n], check_finite=False)


def apply_step(problem: SlamProblem, estimate: Estimate, step: np.ndarray) -> Estimate:
    """Return the estimate moved by a stacked step (poses then landmarks), angles wrapped."""
    poses = estimate.poses + step[: 3 * problem.num_poses].reshape(-1, 3)
    poses[:, 2] = wrap_angle(poses[:, 2])
    return Estimate(poses, estimate.landmarks + step[3 * problem.num_poses :].reshape(-1, 2))


def dense_cost(problem: SlamProblem, estimate: Estimate) -> float:
    """Return 0.5 ||whitened residual||^2 at the estimate."""
    residual, _ = build_linear_system(problem, estimate)
    return 0.5 * float(residual @ residual)


def time_dense(bench: BenchProblem, repeats: int) -> float:
    """Return the median time (ms) of one dense iteration: linearize, QR, solve, step cost."""
    samples = []
    for _ in range(repeats):
        started = time.perf_counter()
        step = dense_step(bench.problem, bench.initial)
        dense_cost(bench.problem, apply_step(bench.problem, bench.initial, step))
        samples.append(time.perf_counter() - started)
    return 1e3 * statistics.median(samples)


def dense_gauss_newton(bench: BenchProblem, max_iterations: int = 50) -> tuple[Estimate, int]:
    """Return the dense Gauss-Newton estimate (full steps while the cost drops), iterations."""
    estimate, cost = bench.initial, dense_cost(bench.problem, bench.initial)
    for iteration in range(1, max_iterations + 1):
        trial = apply_step(bench.problem, estimate, dense_step(bench.problem, estimate))
        trial_cost = dense_cost(bench.problem, trial)
        if not trial_cost < cost:
            return estimate, iteration
        converged = cost - trial_cost <= 1e-10 * cost
        estimate, cost = trial, trial_cost
        if converged:
            return estimate, iteration
    return estimate, max_iterations


def em_pattern(num_poses: int, seed: int) -> tuple[float, list[int]]:
    """Return the time (ms) of 10 LM solves as the EM loop makes them, and their iterations."""
    bench = random_walk_problem(num_poses, seed=seed)
    rng = np.random.default_rng(seed + 1)
    started = time.perf_counter()
    estimate, iterations = bench.initial, []
    for round_index in range(10):
        scale = None
        if round_index:
            weights = rng.uniform(0.3, 1.0, bench.problem.num_landmarks)
            scale = np.maximum(weights[bench.problem.obs_landmark], 1e-3)
        result = solve(bench.problem, estimate, obs_row_scale=scale, method='levenberg_marquardt')
        estimate = result.estimate
        iterations.append(result.iterations)
    return 1e3 * (time.perf_counter() - started), iterations


def growth_exponent(sizes: list[int], times_ms: list[float]) -> float:
    """Return the slope of log(time) against log(size), least squares."""
    if len(sizes) < 2:
        return float('nan')
    slope, _ = np.polyfit(np.log(sizes), np.log(times_ms), 1)
    return float(slope)


@dataclass(frozen=True)
class Row:
    """One table row: a problem, our timing and (maybe) the dense reference."""

    label: str
    problem: SlamProblem
    ours: OursTiming
    dense_ms: float | None


def _fmt(value: float | None, digits: int = 2) -> str:
    return '—' if value is None else f'{value:.{digits}f}'


def render_report(
    rows: list[Row],
    *,
    dense_max_poses: int,
    agreement_m: float,
    dense_iterations: int,
    em: tuple[int, float, list[int]],
    passed: bool,
) -> str:
    """Return the Markdown report."""
    now = datetime.datetime.now(datetime.UTC).strftime('%Y-%m-%d %H:%M UTC')
    lines = [
        '# EM-SAM solver: sparse Gauss-Newton vs dense QR, per iteration',
        '',
        f'{now}; {platform.platform()}, {os.cpu_count()} CPUs, Python '
        f'{platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}; '
        f'commit {source_revision()}.',
        '',
        '| problem | poses | landmarks | observations | unknowns | ours ms/iteration '
        '| linearize+assemble ms/it | factorize+solve ms/it | GN iterations (status) '
        '| LM iterations (status) | first solve ms | dense QR ms/iteration '
        '| dense / ours |',
        '|---|---:|---:|---:|---:|---:|---:|---:|---|---|---:|---:|---:|',
    ]
    for row in rows:
        ours, problem = row.ours, row.problem
        ratio = None if row.dense_ms is None else row.dense_ms / ours.ms_per_iteration
        unknowns = 3 * problem.num_poses + 2 * problem.num_landmarks
        dense = _fmt(row.dense_ms, 1) if row.dense_ms is not None else 'skipped'
        lines.append(
            f'| {row.label} | {problem.num_poses} | {problem.num_landmarks} '
            f'| {problem.num_observations} | {unknowns} | {ours.ms_per_iteration:.2f} '
            f'| {ours.linearize_ms_per_iteration:.2f} | {ours.factorize_ms_per_iteration:.2f} '
            f'| {ours.iterations} ({ours.status}) | {ours.lm_iterations} ({ours.lm_status}) '
            f'| {ours.first_solve_ms:.1f} | {dense} | {_fmt(ratio, 0)} |'
        )
    scaling = [row for row in rows if row.problem.num_poses >= 1000]
    ours_slope = growth_exponent(
        [row.problem.num_poses for row in scaling], [row.ours.ms_per_iteration for row in scaling]
    )
    dense_rows = [row for row in scaling if row.dense_ms is not None]
    dense_slope = growth_exponent(
        [row.problem.num_poses for row in dense_rows],
        [float(row.dense_ms) for row in dense_rows if row.dense_ms is not None],
    )
    paper = rows[0].ours.ms_per_iteration
    em_poses, em_ms, em_iterations = em
    lines += [
        '',
        f'Growth exponent (log-log least-squares fit of time per iteration against poses, '
        f'{len(scaling)} sizes >= 1000 poses): ours **{ours_slope:.2f}**; dense reference '
        f'{dense_slope:.2f} ({len(dense_rows)} sizes >= 1000 poses).',
        '',
        f'Dense reference skipped above {dense_max_poses} poses: the QR of [J | r] costs '
        f'O(m n^2) time and O(m n) memory (m rows, n unknowns); see the README for numbers.',
        '',
        f'Same answer: on the {PAPER_POSES}-pose problem dense Gauss-Newton took '
        f'{dense_iterations} iterations and its estimate differs from ours by at most '
        f'{agreement_m:.1e} (m or rad).',
        '',
        f'EM pattern ({em_poses} poses, 10 Levenberg-Marquardt solves, the first from dead '
        f'reckoning, then warm-started with new row scales): **{em_ms:.0f} ms** in total; '
        f'iterations per solve {em_iterations}.',
        '',
        f'Acceptance: at most {ACCEPT_MS_PER_ITERATION:.0f} ms per Gauss-Newton iteration on '
        f'the {PAPER_POSES}-pose / {rows[0].problem.num_observations}-measurement problem: '
        f'{paper:.2f} ms -> **{"PASS" if passed else "FAIL"}**.',
        '',
    ]
    return '\n'.join(lines)


def plot(rows: list[Row], path: Path) -> None:
    """Write a log-log plot of time per iteration against poses (ours and dense) to path."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7, 4.5))
    poses = [row.problem.num_poses for row in rows]
    axes.loglog(poses, [row.ours.ms_per_iteration for row in rows], 'o-', label='ours (sparse)')
    dense = [(row.problem.num_poses, row.dense_ms) for row in rows if row.dense_ms is not None]
    if dense:
        axes.loglog(*zip(*dense, strict=True), 's--', label='dense QR reference')
    axes.axhline(
        ACCEPT_MS_PER_ITERATION, color='grey', linestyle=':', label='5 ms target (50-pose problem)'
    )
    axes.set_xlabel('poses')
    axes.set_ylabel('time per Gauss-Newton iteration (ms)')
    axes.set_title('EM-SAM solver scaling')
    axes.grid(True, which='both', alpha=0.3)
    axes.legend()
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=120)
    plt.close(figure)


def build_arg_parser() -> argparse.ArgumentParser:
    """Return the command-line parser."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument(
        '--sizes',
        type=int,
        nargs='+',
        default=list(DEFAULT_SIZES),
        help='poses of the scaling problems (the 50-pose paper problem always runs first)',
    )
    parser.add_argument(
        '--dense-max-poses',
        type=int,
        default=2000,
        help='largest problem on which the dense QR reference runs (0: paper problem only)',
    )
    parser.add_argument('--seed', type=int, default=0, help='seed of every problem')
    parser.add_argument(
        '--em-poses', type=int, default=2000, help='poses of the EM-pattern problem'
    )
    parser.add_argument('--no-lm', action='store_true', help='skip the LM iteration counts')
    parser.add_argument('--output', type=Path, default=DEFAULT_OUTPUT, help='Markdown report')
    parser.add_argument('--plot', type=Path, default=DEFAULT_PLOT, help='PNG plot')
    return parser


def run_benchmark(args: argparse.Namespace) -> int:
    """Run every size, write the report and plot; return 0 on PASS, 1 on FAIL."""
    rows = []
    agreement, dense_iterations = float('nan'), 0
    for num_poses in [PAPER_POSES, *args.sizes]:
        bench = random_walk_problem(num_poses, seed=args.seed)
        system_layout(bench.problem)  # validation and index arrays, outside the timings
        repeats = int(np.clip(20_000 // num_poses, 1, 50))
        ours = time_ours(bench, repeats, with_lm=not args.no_lm)
        dense_ms = None
        if num_poses <= args.dense_max_poses:
            dense_ms = time_dense(bench, repeats=5 if num_poses <= 200 else 1)
        if num_poses == PAPER_POSES:
            dense_estimate, dense_iterations = dense_gauss_newton(bench)
            agreement = float(
                max(
                    np.abs(dense_estimate.poses[:, :2] - ours.result.estimate.poses[:, :2]).max(),
                    np.abs(
                        wrap_angle(dense_estimate.poses[:, 2] - ours.result.estimate.poses[:, 2])
                    ).max(),
                    np.abs(dense_estimate.landmarks - ours.result.estimate.landmarks).max(),
                )
            )
        label = 'paper (a)' if num_poses == PAPER_POSES else 'scaling (b)'
        rows.append(Row(label, bench.problem, ours, dense_ms))
        dense_text = 'skipped' if dense_ms is None else f'{dense_ms:.1f} ms'
        print(
            f'{num_poses:>6} poses: ours {ours.ms_per_iteration:.2f} ms/iteration, '
            f'{ours.iterations} GN iterations ({ours.status}); dense {dense_text}',
            flush=True,
        )
    em_ms, em_iterations = em_pattern(args.em_poses, args.seed)
    passed = rows[0].ours.ms_per_iteration <= ACCEPT_MS_PER_ITERATION
    report = render_report(
        rows,
        dense_max_poses=args.dense_max_poses,
        agreement_m=agreement,
        dense_iterations=dense_iterations,
        em=(args.em_poses, em_ms, em_iterations),
        passed=passed,
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(report)
    plot(rows, args.plot)
    print(report)
    print(f'report: {args.output}; plot: {args.plot}')
    print('PASS' if passed else 'FAIL')
    return 0 if passed else 1


def main(argv: list[str] | None = None) -> int:
    """Parse arguments and run the benchmark."""
    return run_benchmark(build_arg_parser().parse_args(argv))


if __name__ == '__main__':
    sys.exit(main())
