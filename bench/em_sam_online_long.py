"""Benchmark: EM-SAM online on a 100k-keyframe run, against plain GTSAM iSAM2 on the same
factors, one keyframe per update; latency over time and peak memory.

    python bench/em_sam_online_long.py [--copies 56] [--output bench/results]

The run is the office bag (bags/office_moveable.mcap, 1802 keyframes, 10 moved markers)
replayed through the nodes' processors and tiled ``--copies`` times into one trajectory
(``em_sam_office.tile``: each copy with its own landmark ids, chained by odometry; 56 copies
are 100,912 keyframes). Each solver runs in a fresh process, so its peak resident memory
is its own:

- reference: GTSAM iSAM2 with its default parameters, one ``update`` per keyframe with the
  increment's relative pose (``core.incremental.between_of_increment``) and the keyframe's
  bearing-range sightings, every landmark static, the moved markers' sightings left out
  (the oracle's factors: with them, iSAM2's steps diverge at the first move and GTSAM
  stops with an indeterminate system);
- ours: ``IncrementalEmSam`` (default EmConfig and IncrementalConfig).

Per solver: latency per update (mean, median, p95, max, ms), per window of ``WINDOW``
keyframes (mean and p95), peak memory, and for ours the flagged landmarks (10 per copy
expected) and the static ones flagged at any keyframe.

Acceptance (issue 44): ours p95 <= 50 ms; no upward trend over the second half (the
least-squares line through the windows' p95 over the second half rises by less than 10 %
of its mean across it); peak memory < 4 GB. PASS or FAIL per point; any FAIL exits 1.
Writes ``em_sam_online_long.md`` and a PNG of the windows' mean and p95 to ``--output``.
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))

from bench_common import run_meta  # noqa: E402
from em_sam_office import tile  # noqa: E402

from em_sam_node.core.assembly import MappingData  # noqa: E402
from em_sam_node.core.em_types import EmConfig  # noqa: E402
from em_sam_node.core.incremental import IncrementalEmSam  # noqa: E402
from em_sam_node.core.incremental_parts import between_of_increment, load_gtsam  # noqa: E402
from em_sam_node.offline import replay_bag  # noqa: E402
from slam_core.blas import single_threaded_blas  # noqa: E402
from slam_core.files import write_atomically  # noqa: E402

BAG = ROOT / 'bags' / 'office_moveable.mcap'
MOVED = range(100, 110)  # the office bag's moved markers (each copy offsets the ids)
WINDOW = 1000  # keyframes per point of the latency-over-time table and plot
P95_MAX_MS, MEMORY_MAX_GB, TREND_MAX = 50.0, 4.0, 0.10
PROGRESS_EVERY = 5000


def _keyframes(data: MappingData) -> list[tuple[Any, list[int]]]:
    """Per keyframe: its increment (u, cov) or None, and its sighting rows."""
    incoming = {int(to): m for m, to in enumerate(data.odometry_to.tolist())}
    rows_of: dict[int, list[int]] = {}
    for k, keyframe in enumerate(data.obs_keyframe.tolist()):
        rows_of.setdefault(keyframe, []).append(k)
    result = []
    for index in range(data.num_keyframes):
        m = incoming.get(index)
        odometry = None if m is None else (data.odometry_u[m], data.odometry_cov[m])
        result.append((odometry, rows_of.get(index, [])))
    return result


def _progress(name: str, index: int, total: int, started: float) -> None:
    if index and index % PROGRESS_EVERY == 0:
        elapsed = time.perf_counter() - started
        eta = elapsed / index * (total - index)
        print(
            f'em_sam_online_long: {name} {index}/{total} keyframes, '
            f'{index / elapsed:.0f}/s, ETA {eta:.0f} s',
            file=sys.stderr,
        )


def run_reference(data: MappingData, moved: set[int]) -> dict[str, Any]:
    """Plain iSAM2 on the same factors without the moved markers' (the oracle's factors):
    with them at full weight its Gauss-Newton steps diverge on the first move and GTSAM
    stops (indeterminate system)."""
    gtsam = load_gtsam()
    solver = gtsam.ISAM2(gtsam.ISAM2Params())
    known: set[int] = set()
    latencies = []
    keyframes = _keyframes(data)
    started = time.perf_counter()
    for index, (odometry, rows) in enumerate(keyframes):
        _progress('iSAM2', index, len(keyframes), started)
        begin = time.perf_counter()
        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if odometry is None:
            start = gtsam.Pose2(*data.prior_pose)
            noise = gtsam.noiseModel.Gaussian.Covariance(data.prior_cov)
            factors.add(gtsam.PriorFactorPose2(index, start, noise))
        else:
            between, covariance = between_of_increment(odometry[0], odometry[1][None])
            relative = gtsam.Pose2(*between[0])
            start = solver.calculateEstimatePose2(index - 1).compose(relative)
            noise = gtsam.noiseModel.Gaussian.Covariance(covariance[0])
            factors.add(gtsam.BetweenFactorPose2(index - 1, index, relative, noise))
        values.insert(index, start)
        for k in rows:
            landmark, z = int(data.obs_landmark_id[k]), data.obs_z[k]
            if landmark in moved:
                continue
            symbol = gtsam.symbol('l', landmark)
            if landmark not in known:
                known.add(landmark)
                seen = gtsam.Point2(z[0] * np.cos(z[1]), z[0] * np.sin(z[1]))
                values.insert(symbol, start.transformFrom(seen))
            cov = data.obs_cov[k][np.ix_([1, 0], [1, 0])]  # (bearing, range) order
            noise = gtsam.noiseModel.Gaussian.Covariance(cov)
            factors.add(
                gtsam.BearingRangeFactor2D(
                    index, symbol, gtsam.Rot2(float(z[1])), float(z[0]), noise
                )
            )
        solver.update(factors, values)
        latencies.append(time.perf_counter() - begin)
    return {'latencies': latencies}


def run_ours(data: MappingData, moved: set[int]) -> dict[str, Any]:
    """IncrementalEmSam; its latencies, flagged landmarks and statics flagged on the way."""
    smoother = IncrementalEmSam(EmConfig(), data.prior_pose, data.prior_cov)
    latencies: list[float] = []
    wrongly: set[int] = set()
    keyframes = _keyframes(data)
    started = time.perf_counter()
    for index, (odometry, rows) in enumerate(keyframes):
        _progress('ours', index, len(keyframes), started)
        sightings = [(int(data.obs_landmark_id[k]), data.obs_z[k], data.obs_cov[k]) for k in rows]
        step = smoother.add_keyframe(odometry, sightings)
        latencies.append(step.seconds)
        wrongly |= step.moveable - moved
    return {
        'latencies': latencies,
        'flagged': len(smoother.moveable),
        'missed': len(moved - smoother.moveable),
        'expected': len(moved),
        'statics_flagged': sorted(wrongly),
    }


def _child(which: str, copies: int, queue: multiprocessing.Queue) -> None:
    single_threaded_blas()
    base = replay_bag(BAG).data
    data = tile(base, copies)
    offset = int(base.obs_landmark_id.max()) + 1  # tile's id offset per copy
    moved = {i + c * offset for c in range(copies) for i in MOVED}
    result = run_ours(data, moved) if which == 'ours' else run_reference(data, moved)
    result['peak_gb'] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    result['keyframes'] = data.num_keyframes
    queue.put(result)


def _measure(which: str, copies: int) -> dict[str, Any]:
    context = multiprocessing.get_context('spawn')
    queue = context.Queue()
    process = context.Process(target=_child, args=(which, copies, queue))
    process.start()
    result: dict[str, Any] = queue.get()
    process.join()
    return result


def windows(latencies: list[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per window of WINDOW keyframes: its middle keyframe, mean and p95 (ms)."""
    ms = np.asarray(latencies) * 1e3
    count = len(ms) // WINDOW
    blocks = ms[: count * WINDOW].reshape(count, WINDOW)
    middle = np.arange(count) * WINDOW + WINDOW / 2
    return middle, blocks.mean(axis=1), np.percentile(blocks, 95, axis=1)


def second_half_rise(latencies: list[float]) -> float:
    """The rise across the second half of the line fitted to the windows' p95, over its
    mean: 0 flat, 0.1 a 10 % rise."""
    middle, _, p95 = windows(latencies)
    half = middle >= middle[-1] / 2
    slope, _ = np.polyfit(middle[half], p95[half], 1)
    span = middle[half][-1] - middle[half][0]
    return float(slope * span / np.mean(p95[half]))


def _stats(latencies: list[float]) -> tuple[float, float, float, float]:
    ms = np.asarray(latencies) * 1e3
    return float(ms.mean()), float(np.median(ms)), float(np.percentile(ms, 95)), float(ms.max())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--copies', type=int, default=56, help='office runs tiled (56: ~100k)')
    parser.add_argument('--output', type=Path, default=ROOT / 'bench' / 'results')
    args = parser.parse_args()
    if args.copies < 2:
        parser.error('--copies must be at least 2 (the trend is over the second half)')
    print(f'em_sam_online_long: {args.copies} office runs, iSAM2 ...', file=sys.stderr)
    reference = _measure('reference', args.copies)
    print('em_sam_online_long: ours ...', file=sys.stderr)
    ours = _measure('ours', args.copies)
    lines = [
        f'# EM-SAM online against iSAM2: {ours["keyframes"]} keyframes '
        f'({args.copies} office runs), one per update',
        '',
        ', '.join(f'{k} {v}' for k, v in run_meta('not pinned').items()),
        '',
        '| solver | mean ms | median ms | p95 ms | max ms | mean / iSAM2 | peak memory GB |',
        '|---|---|---|---|---|---|---|',
    ]
    reference_mean = _stats(reference['latencies'])[0]
    for name, result in (('GTSAM iSAM2 (reference)', reference), ('EM-SAM online (ours)', ours)):
        mean, median, p95, peak = _stats(result['latencies'])
        lines.append(
            f'| {name} | {mean:.2f} | {median:.2f} | {p95:.2f} | {peak:.1f} | '
            f'{mean / reference_mean:.2f} | {result["peak_gb"]:.2f} |'
        )
    lines += [
        '',
        f'Ours flagged {ours["flagged"]} landmarks, missed {ours["missed"]} of the '
        f'{ours["expected"]} moved; static landmarks flagged at some keyframe: '
        f'{ours["statics_flagged"] or "none"}.',
        '',
        f'| keyframes (window of {WINDOW}) | iSAM2 mean ms | iSAM2 p95 ms | ours mean ms | '
        'ours p95 ms |',
        '|---|---|---|---|---|',
    ]
    middle, ref_mean, ref_p95 = windows(reference['latencies'])
    _, our_mean, our_p95 = windows(ours['latencies'])
    step = max(1, len(middle) // 20)
    for i in range(0, len(middle), step):
        lines.append(
            f'| {int(middle[i])} | {ref_mean[i]:.2f} | {ref_p95[i]:.2f} | {our_mean[i]:.2f} | '
            f'{our_p95[i]:.2f} |'
        )
    _, _, p95, _ = _stats(ours['latencies'])
    rise = second_half_rise(ours['latencies'])
    checks = [
        (f'ours p95 {p95:.1f} ms <= {P95_MAX_MS:g} ms', p95 <= P95_MAX_MS),
        (
            f'second half: p95 line rises {100 * rise:.1f} % (< {100 * TREND_MAX:g} %)',
            rise < TREND_MAX,
        ),
        (
            f'peak memory {ours["peak_gb"]:.2f} GB < {MEMORY_MAX_GB:g} GB',
            ours['peak_gb'] < MEMORY_MAX_GB,
        ),
    ]
    lines += ['', *(f'- {"PASS" if ok else "FAIL"}: {text}' for text, ok in checks), '']
    text = '\n'.join(lines)
    print(text)
    args.output.mkdir(parents=True, exist_ok=True)
    write_atomically(args.output / 'em_sam_online_long.md', text)
    _plot(args.output / 'em_sam_online_long.png', middle, ref_mean, ref_p95, our_mean, our_p95)
    return 0 if all(ok for _, ok in checks) else 1


def _plot(path: Path, middle: np.ndarray, *series: np.ndarray) -> None:
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(9, 4.5))
    labels = ('iSAM2 mean', 'iSAM2 p95', 'ours mean', 'ours p95')
    styles = ('C0-', 'C0--', 'C1-', 'C1--')
    for values, label, style in zip(series, labels, styles, strict=True):
        axis.plot(middle, values, style, label=label)
    axis.set_xlabel('keyframe')
    axis.set_ylabel(f'latency per update, ms (window of {WINDOW})')
    axis.set_title('EM-SAM online against iSAM2, one keyframe per update')
    axis.legend()
    axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


if __name__ == '__main__':
    raise SystemExit(main())
