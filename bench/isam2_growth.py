"""Benchmark: GTSAM iSAM2's own latency per update over a long odometry chain, with the whole
history in the smoother and with the poses older than a horizon marginalized.

    python bench/isam2_growth.py [--poses 40000] [--horizon 1000] [--output bench/results]

One pose per update, a between factor to the one before (a prior on the first), nothing
else: no landmarks, no removals, no lookups. Variants, each in a fresh process:

- whole: iSAM2 as ``IncrementalEmSam`` configures it (partial relinearization check), every
  pose kept;
- horizon: the same, and after each update the pose ``horizon`` keyframes back is
  marginalized (``ISAM2.marginalizeLeaves``), so the smoother holds at most ``horizon``
  poses.

Per variant, per tenth of the run: the mean update time (ms); and the last tenth's mean over
the first's. If the whole chain's grows with the run while the horizon's stays flat, the
growth is the smoother's size, not the work an update has to do (each update touches the
same few variables). Writes ``isam2_growth.md`` to ``--output``.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import multiprocessing
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))

from bench_common import run_meta  # noqa: E402

from em_sam_node.core.incremental_parts import load_gtsam  # noqa: E402
from slam_core.blas import single_threaded_blas  # noqa: E402
from slam_core.files import write_atomically  # noqa: E402

PARTS = 10  # the run is reported per tenth
STEP = (0.1, 0.0, 0.01)  # m, m, rad per pose: a wide circle
SIGMAS = (0.05, 0.05, 0.01)


def run_chain(poses: int, horizon: int | None) -> list[float]:
    """Update times (s) of an odometry chain of ``poses``; with ``horizon``, the pose that
    many back is marginalized after each update (inside the timed span)."""
    gtsam = load_gtsam()
    params = gtsam.ISAM2Params()
    params.enablePartialRelinearizationCheck = True
    solver = gtsam.ISAM2(params)
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(SIGMAS))
    step, pose = gtsam.Pose2(*STEP), gtsam.Pose2()
    times = []
    for index in range(poses):
        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if index == 0:
            factors.add(gtsam.PriorFactorPose2(0, pose, noise))
        else:
            factors.add(gtsam.BetweenFactorPose2(index - 1, index, step, noise))
            pose = pose.compose(step)
        values.insert(index, pose)
        started = time.perf_counter()
        solver.update(factors, values)
        if horizon is not None and index >= horizon:
            leaves = gtsam.KeyList()
            leaves.push_back(index - horizon)
            solver.marginalizeLeaves(leaves)
        times.append(time.perf_counter() - started)
    return times


def _child(poses: int, horizon: int | None, queue: multiprocessing.Queue) -> None:
    single_threaded_blas()
    queue.put(run_chain(poses, horizon))


def _measure(poses: int, horizon: int | None) -> list[float]:
    context = multiprocessing.get_context('spawn')
    queue = context.Queue()
    process = context.Process(target=_child, args=(poses, horizon, queue))
    process.start()
    times: list[float] = queue.get()
    process.join()
    return times


def per_part(times: list[float]) -> np.ndarray:
    """Mean update time (ms) per tenth of the run."""
    ms = np.asarray(times) * 1e3
    return np.array([part.mean() for part in np.array_split(ms, PARTS)])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--poses', type=int, default=40000, help='poses in the chain')
    parser.add_argument('--horizon', type=int, default=1000, help='poses kept (horizon run)')
    parser.add_argument('--output', type=Path, default=ROOT / 'bench' / 'results')
    args = parser.parse_args()
    if args.poses < PARTS * 10 or not 0 < args.horizon < args.poses:
        parser.error('need --poses >= 100 and 0 < --horizon < --poses')
    results = {}
    for name, horizon in (('whole', None), (f'horizon {args.horizon}', args.horizon)):
        print(f'isam2_growth: {name}, {args.poses} poses ...', file=sys.stderr)
        results[name] = per_part(_measure(args.poses, horizon))
    names = list(results)
    lines = [
        f'# GTSAM {importlib.metadata.version("gtsam")} iSAM2 on an odometry chain of '
        f'{args.poses} poses, one per update',
        '',
        ', '.join(f'{k} {v}' for k, v in run_meta('not pinned').items()),
        '',
        '| poses | ' + ' | '.join(f'{n}: mean ms' for n in names) + ' |',
        '|---' * (len(names) + 1) + '|',
    ]
    bounds = np.linspace(0, args.poses, PARTS + 1).astype(int)
    for part in range(PARTS):
        cells = ' | '.join(f'{results[n][part]:.3f}' for n in names)
        lines.append(f'| {bounds[part]}-{bounds[part + 1]} | {cells} |')
    lines.append('')
    lines += [
        f'- {n}: last tenth / first tenth = {results[n][-1] / results[n][0]:.1f}x' for n in names
    ]
    text = '\n'.join([*lines, ''])
    print(text)
    args.output.mkdir(parents=True, exist_ok=True)
    write_atomically(args.output / 'isam2_growth.md', text)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
