"""Benchmark: EM-SAM online (``em_sam_node.core.incremental``) against GTSAM iSAM2, one
keyframe per update, side by side in the same run.

    python bench/em_sam_online.py [--keyframes N] [--output bench/results]

Victoria Park (the data root's ``victoria_park/victoria_park.txt``), replayed one pose at a
time as em_sam_mapper gets it (``victoria_park_gtsam.mapping_data``: eq. 2 increments and
range-bearing sightings):

- reference: GTSAM 4.3 iSAM2 with its default parameters, one ``update`` per pose with its
  odometry factor and sightings, every tree static (``victoria_park_gtsam.isam2``, timed
  per update);
- ours: ``IncrementalEmSam`` with the default EmConfig (robust mode) and IncrementalConfig:
  the same iSAM2 underneath, plus each keyframe's EM test of the trees it saw and the
  replacement of the factors whose weight or gate changed.

The two advance together, one update of each per keyframe, the first to go alternating
(``bench_common.side_by_side``): the machine's load, which drifts on a shared VM, falls on
both alike. Per row: latency per update (mean, median, p95, max, ms), the ratio of the
means, the cost of the last estimate on GTSAM's full all-static graph, and ours's flagged
trees. Then the polish a full pass starts from: our Levenberg-Marquardt
(``core.solver.solve``, all static) from ours's last estimate, its cost against the best
known (2339.2, GTSAM LM from iSAM2's estimate; issue 44).

Then the full pass (``run_em`` from dead reckoning) scored with its flagged trees left out,
in the nominal odometry model and in the model it estimates (its odometry calibration),
each against the best cost known in that model (``full_pass``).

Acceptance (issue 44): ours p95 <= 50 ms, max <= 500 ms, mean <= iSAM2's; at most 3 trees
flagged; the polished cost <= 1.01 x 2339.2; the full pass's cost in its own model <= 1.01 x
the best known there. PASS or FAIL per point; any FAIL exits 1.
Writes ``em_sam_online.md`` and a plot of the latency's mean and p95 per 100 keyframes
(PNG) to ``--output``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))

from bench_common import run_meta, side_by_side  # noqa: E402
from victoria_park_gtsam import (  # noqa: E402
    from_values,
    gtsam_graph,
    isam2_updates,
    mapping_data,
    our_problem,
)

from em_sam_node.core.assembly import (  # noqa: E402
    BuiltProblem,
    MappingData,
    build_problem,
    initial_estimate,
)
from em_sam_node.core.em import run_em  # noqa: E402
from em_sam_node.core.em_types import EmConfig, EmResult  # noqa: E402
from em_sam_node.core.factors import (  # noqa: E402
    observation_residuals,
    odometry_residuals,
    prior_residual,
)
from em_sam_node.core.incremental import IncrementalEmSam  # noqa: E402
from em_sam_node.core.incremental_parts import load_gtsam  # noqa: E402
from em_sam_node.core.incremental_types import UpdateStats  # noqa: E402
from em_sam_node.core.odometry_calibration import OdometryCalibration  # noqa: E402
from em_sam_node.core.problem import Estimate, SlamProblem, SolveResult  # noqa: E402
from em_sam_node.core.solver import solve  # noqa: E402
from slam_core.blas import single_threaded_blas  # noqa: E402
from slam_core.datasets import data_root  # noqa: E402
from slam_core.files import write_atomically  # noqa: E402
from slam_sim.core.victoria_park import parse_victoria_park  # noqa: E402

BEST_KNOWN_COST = 2339.2  # GTSAM LM polished from iSAM2's estimate (issue 44)
P95_MAX_MS, MAX_MS, MAX_FLAGGED, COST_RATIO = 50.0, 500.0, 3, 1.01
PLOT_WINDOW = 100  # keyframes per point of the latency plot


def online_updates(
    smoother: IncrementalEmSam, data: MappingData, count: int
) -> Iterator[UpdateStats]:
    """Feed ``smoother`` the first ``count`` keyframes of ``data``, one ``add_keyframe``
    per ``next``; yields its UpdateStats."""
    incoming = {int(to): m for m, to in enumerate(data.odometry_to.tolist())}
    rows_of: dict[int, list[int]] = {}
    for k, keyframe in enumerate(data.obs_keyframe.tolist()):
        rows_of.setdefault(keyframe, []).append(k)
    for index in range(count):
        m = incoming.get(index)
        odometry = None if m is None else (data.odometry_u[m], data.odometry_cov[m])
        sightings = [
            (int(data.obs_landmark_id[k]), data.obs_z[k], data.obs_cov[k])
            for k in rows_of.get(index, [])
        ]
        yield smoother.add_keyframe(odometry, sightings)


def _stats(latencies: list[float]) -> tuple[float, float, float, float]:
    ms = np.asarray(latencies) * 1e3
    return float(ms.mean()), float(np.median(ms)), float(np.percentile(ms, 95)), float(ms.max())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--keyframes', type=int, default=None, help='only the first N poses')
    parser.add_argument('--output', type=Path, default=ROOT / 'bench' / 'results')
    args = parser.parse_args()
    single_threaded_blas()
    gtsam = load_gtsam()
    data = parse_victoria_park(data_root() / 'victoria_park' / 'victoria_park.txt')
    count = min(args.keyframes or data.num_poses, data.num_poses)
    problem, start = our_problem(data)
    graph, _ = gtsam_graph(gtsam, data, start)
    landmark_ids = np.unique(data.obs_landmark)

    print(f'em_sam_online: Victoria Park, {count} poses, iSAM2 and ours ...', file=sys.stderr)
    solver = gtsam.ISAM2(gtsam.ISAM2Params())
    ours_data = mapping_data(data)
    smoother = IncrementalEmSam(EmConfig(), ours_data.prior_pose, ours_data.prior_cov)
    (plain, ours), failures = side_by_side(
        [
            isam2_updates(gtsam, graph, data, solver, count),
            online_updates(smoother, ours_data, count),
        ],
        count,
    )
    if any(failures):
        raise RuntimeError(f'a solver failed: {failures}')
    reference = solver.calculateEstimate()
    rows = [('GTSAM iSAM2 (reference)', plain), ('EM-SAM online (ours)', ours)]
    lines = [
        f'# EM-SAM online against iSAM2: Victoria Park, {count} poses, one per update',
        '',
        ', '.join(f'{k} {v}' for k, v in run_meta('not pinned').items()),
        '',
        '| solver | mean ms | median ms | p95 ms | max ms | mean / iSAM2 |',
        '|---|---|---|---|---|---|',
    ]
    reference_mean = _stats(plain)[0]
    for name, latencies in rows:
        mean, median, p95, peak = _stats(latencies)
        lines.append(
            f'| {name} | {mean:.2f} | {median:.2f} | {p95:.2f} | {peak:.1f} | '
            f'{mean / reference_mean:.2f} |'
        )
    mean, _, p95, peak = _stats(ours)
    checks = [
        (f'ours p95 {p95:.1f} ms <= {P95_MAX_MS:g} ms', p95 <= P95_MAX_MS),
        (f'ours max {peak:.1f} ms <= {MAX_MS:g} ms', peak <= MAX_MS),
        (f"ours mean {mean:.2f} ms <= iSAM2's {reference_mean:.2f} ms", mean <= reference_mean),
        (
            f'trees flagged {sorted(smoother.moveable)}: at most {MAX_FLAGGED}',
            len(smoother.moveable) <= MAX_FLAGGED,
        ),
    ]
    if count == data.num_poses:
        poses = smoother.poses()
        positions = smoother.landmark_positions()
        ours_estimate = Estimate(poses, np.array([positions[int(j)] for j in landmark_ids]))
        reference_estimate = from_values(gtsam, reference, count, landmark_ids)
        costs = {
            'iSAM2': _cost(gtsam, graph, reference_estimate, landmark_ids),
            'ours': _cost(gtsam, graph, ours_estimate, landmark_ids),
        }
        started = time.perf_counter()
        polished = solve(problem, ours_estimate, method='levenberg_marquardt', max_iterations=200)
        seconds = time.perf_counter() - started
        costs['ours, polished (LM, all static)'] = _cost(
            gtsam, graph, polished.estimate, landmark_ids
        )
        lines += ['', '| last estimate | cost on the full graph |', '|---|---|']
        lines += [f'| {name} | {cost:.1f} |' for name, cost in costs.items()]
        lines.append(f'\nThe polish took {seconds:.1f} s.')
        polished_cost = costs['ours, polished (LM, all static)']
        checks.append(
            (
                f'polished cost {polished_cost:.1f} <= {COST_RATIO} x {BEST_KNOWN_COST}',
                polished_cost <= COST_RATIO * BEST_KNOWN_COST,
            )
        )
        full_lines, full_checks = full_pass(mapping_data(data), ours_estimate.poses)
        lines += full_lines
        checks += full_checks
    lines += ['', *(f'- {"PASS" if ok else "FAIL"}: {text}' for text, ok in checks)]
    report = '\n'.join(lines) + '\n'
    print(report)
    args.output.mkdir(parents=True, exist_ok=True)
    write_atomically(args.output / 'em_sam_online.md', report)
    _plot(args.output / 'em_sam_online.png', rows)
    return 0 if all(ok for _, ok in checks) else 1


def full_pass(
    data: MappingData, online_poses: np.ndarray
) -> tuple[list[str], list[tuple[str, bool]]]:
    """The full pass (``run_em``, default EmConfig, from dead reckoning, as the mapper's
    first ``optimize``) scored in two models with its flagged trees left out: the nominal
    odometry, and the odometry calibrated as the full pass estimated it (its M-step). In
    each, the best known cost is the lower of our LM from the online estimate and from the
    full pass; the cost of the all-static problem is given for each model as well."""
    started = time.perf_counter()
    result = run_em(data, EmConfig())
    seconds = time.perf_counter() - started
    calibration = OdometryCalibration(*result.odometry_calibration)
    flagged = result.landmark_ids[result.moveable].tolist()
    rows, checks = [], []
    for name, model in (('nominal odometry', OdometryCalibration()), ('calibrated', calibration)):
        calibrated = model.apply(data)
        built = build_problem(calibrated, exclude_ids=flagged)
        ours = _kept(result, built)
        best = min(
            _model_cost(built.problem, _lm(built.problem, start).estimate)
            for start in (ours, initial_estimate(built.problem, online_poses))
        )
        everything = build_problem(calibrated).problem
        all_static = _lm(everything, initial_estimate(everything, online_poses)).estimate
        cost = _model_cost(built.problem, ours)
        rows.append(
            f'| {name} | {cost:.1f} | {best:.1f} | {cost / best:.4f} | '
            f'{_model_cost(everything, all_static):.1f} |'
        )
        if model is calibration:
            checks.append(
                (
                    f'full pass cost in its own model {cost:.1f} <= {COST_RATIO} x best known '
                    f'{best:.1f}',
                    cost <= COST_RATIO * best,
                )
            )
    uncalibrated = run_em(data, dataclasses.replace(EmConfig(), calibrate_odometry=False))
    flagged_nominal = uncalibrated.landmark_ids[uncalibrated.moveable].tolist()
    built = build_problem(data, exclude_ids=flagged_nominal)
    nominal = _model_cost(built.problem, _kept(uncalibrated, built))
    scales = ', '.join(f'{v:.4f}' for v in result.odometry_calibration)
    lines = [
        '',
        f'The full pass (run_em from dead reckoning, {seconds:.1f} s) flags {flagged} and '
        f'calibrates the odometry by (translation, rotation) = ({scales}). Costs without the '
        'flagged trees; the last column is the all-static optimum (LM from the online estimate):',
        '',
        '| odometry model | full pass | best known | ratio | all static, best known |',
        '|---|---|---|---|---|',
        *rows,
        '',
        f'With calibrate_odometry off, the full pass flags {flagged_nominal} and costs '
        f'{nominal:.1f} in the nominal model without them.',
    ]
    return lines, checks


def _kept(result: EmResult, built: BuiltProblem) -> Estimate:
    """``result``'s poses and its positions of ``built``'s landmarks."""
    index = {int(j): k for k, j in enumerate(result.landmark_ids.tolist())}
    positions = [result.positions[index[int(j)]] for j in built.landmark_ids]
    return Estimate(result.poses, np.array(positions))


def _lm(problem: SlamProblem, start: Estimate) -> SolveResult:
    return solve(problem, start, method='levenberg_marquardt', max_iterations=200)


def _model_cost(problem: SlamProblem, estimate: Estimate) -> float:
    """0.5 x the squared whitened residuals (our terms, GTSAM's ``error``)."""
    parts = (
        prior_residual(problem, estimate),
        odometry_residuals(problem, estimate),
        observation_residuals(problem, estimate),
    )
    return 0.5 * sum(float(np.sum(part * part)) for part in parts)


def _cost(gtsam: Any, graph: Any, estimate: Estimate, landmark_ids: np.ndarray) -> float:
    values = gtsam.Values()
    for i, pose in enumerate(estimate.poses):
        values.insert(i, gtsam.Pose2(*pose))
    for j, point in zip(landmark_ids.tolist(), estimate.landmarks, strict=True):
        values.insert(gtsam.symbol('l', j), np.asarray(point, dtype=float))
    return float(graph.error(values))


def _plot(path: Path, rows: list[tuple[str, list[float]]]) -> None:
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(9, 4.5))
    for (name, latencies), colour in zip(rows, ('tab:blue', 'tab:orange'), strict=False):
        ms = np.asarray(latencies) * 1e3
        starts = np.arange(0, len(ms), PLOT_WINDOW)
        windows = [ms[i : i + PLOT_WINDOW] for i in starts]
        centres = starts + PLOT_WINDOW / 2
        axis.plot(centres, [w.mean() for w in windows], color=colour, label=f'{name}: mean')
        axis.plot(
            centres, [np.percentile(w, 95) for w in windows], color=colour, ls='--',
            label=f'{name}: p95',
        )  # fmt: skip
    axis.set_yscale('log')
    axis.set_xlabel(f'keyframe (pose of the run; per {PLOT_WINDOW} keyframes)')
    axis.set_ylabel('update latency, ms (log)')
    axis.set_title('Victoria Park, one pose per update')
    axis.legend(loc='upper left')
    figure.tight_layout()
    write_atomically(path, lambda stream: figure.savefig(stream, format='png', dpi=110))
    plt.close(figure)


if __name__ == '__main__':
    sys.exit(main())
