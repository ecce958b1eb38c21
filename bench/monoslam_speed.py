"""Benchmark: MonoSLAM EKF + Shadow filter frame rate on one core, next to a bare dense EKF.

Inputs are paper 001's Fig. 5 measurement-level scene (``monoslam_evaluate``'s: 200 static
points, 8 objects x 8 moving points, the initialization target's 4 corners as known points,
1 px pixel noise, 30 Hz), seed ``--seed``. Per frame, as the pipeline of variant (c) runs
them, pinned to one CPU (``sched_setaffinity``, BLAS and OpenCV on one thread):

* ``MonoSlam.process`` with a map of at most ``--map-features`` (30) features
  (``initialize='all'``, fed the static features only, so that the map stays full and
  healthy), the known points measured every frame;
* ``ShadowFilter.process`` given SLAM's pose and covariance and ``--shadow-features`` (20)
  features SLAM does not own (the lowest ids, so that the same tracks persist).

SLAM is told the tracker's offsets that persist (``--tracking-offset-px``; default: the
feature tracker's, 1.5 px, as the node graph ``monoslam_shadow.yaml`` declares them to
monoslam), so each feature carries 2 offset states as in the graph; 0 times white noise.

Only frames with the full workload are counted (the map holds ``--map-features`` features
and the Shadow filter got ``--shadow-features``); per pass the median time per frame of
each part, best of ``--repeats`` passes over the whole run.

Reference, in the same run, on the same frames: the textbook dense EKF step of the same
sizes in numpy (state n = SLAM's state size of that frame, m = 2 x its accepted measurements
+ known points): P = F P F' + Q with the 13 x 13 camera block of F dense, S = H P H' + R,
K = P H' S^-1, the Joseph update and x += K y, with a dense H; no measurement model, no
Jacobians, no gating, no map management. Ours / reference is what the model, the sparse
Jacobians and the bookkeeping cost on top of the linear algebra every EKF does.

Acceptance (issue 7): SLAM + Shadow at least 30 frames/s (goal 100) with 30 map features and
20 Shadow features per frame. PASS or FAIL is printed; FAIL exits with 1. The report goes to
``bench/results/monoslam_speed.md`` and ``.json``.

Map-size sweep (issue 21, ``--map-sweep 25,50,75,100,125,150``): the same measurement with
every size as ``--map-features`` (every feature in the state measured in every counted frame:
the worst case for a map of that size, since a persistent map measures only those in view),
SLAM time per frame against the features in the state, with the reference at each size.
Acceptance: MonoSlam.process at least 30 frames/s with 100 features in the state. A size the
scene cannot fill (fewer static points in view at once) is reported as such.

Run (after ``bash scripts/bootstrap.sh``)::

    source scripts/env.sh
    python bench/monoslam_speed.py [--repeats 3] [--seed 0] [--duration-s 20]
"""

from __future__ import annotations

import os

for _variable in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_variable, '1')  # before numpy: one core means one BLAS thread

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import gc  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from bench_common import BENCH_DIR, pin_to_one_core, run_meta  # noqa: E402

from monoslam_shadow_node.common.core.tracking_noise import drift_bounded_offset_px  # noqa: E402
from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig  # noqa: E402
from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam  # noqa: E402
from monoslam_shadow_node.monoslam.core.monoslam_model import CAMERA_SIZE  # noqa: E402
from monoslam_shadow_node.monoslam.core.monoslam_types import (  # noqa: E402
    TRACKING,
    MonoSlamConfig,
    MonoSlamResult,
)
from monoslam_shadow_node.shadow_filter.core.shadow_filter import (  # noqa: E402
    FrameInput,
    ShadowConfig,
    ShadowFilter,
)
from slam_core.arrays import FloatArray  # noqa: E402
from slam_core.camera import CameraModel  # noqa: E402
from slam_core.files import write_atomically  # noqa: E402
from slam_evaluation.monoslam_pipeline import (  # noqa: E402
    MeasurementFrame,
    PipelineConfig,
    simulation_frames,
    target_known_points,
)
from slam_evaluation.shadow_runs import camera_model  # noqa: E402
from slam_sim.core.dynamic_config import DynamicSceneConfig  # noqa: E402
from slam_sim.core.dynamic_scene import simulate_dynamic_scene  # noqa: E402
from slam_sim.core.init_target import InitTarget  # noqa: E402

DEFAULT_OUTPUT = BENCH_DIR / 'results' / 'monoslam_speed.md'
ACCEPT_HZ = 30.0
GOAL_HZ = 100.0


@dataclass
class FrameTimes:
    """One pass: per counted frame the SLAM and Shadow times (s), SLAM's state size and
    measurement rows, and the frames the run had."""

    slam_s: list[float] = dataclasses.field(default_factory=list)
    shadow_s: list[float] = dataclasses.field(default_factory=list)
    state_sizes: list[int] = dataclasses.field(default_factory=list)
    rows: list[int] = dataclasses.field(default_factory=list)
    frames: int = 0

    @property
    def total_s(self) -> FloatArray:
        """Per counted frame SLAM + Shadow time, s."""
        return np.asarray(self.slam_s) + np.asarray(self.shadow_s)


def shadow_input(
    frame: MeasurementFrame, slam: MonoSlam, count: int, result: MonoSlamResult
) -> FrameInput | None:
    """Return the Shadow filter's input for this frame: SLAM's pose, its covariance and its
    covariances with the earlier poses' (as the pipeline passes them) and the ``count``
    lowest ids SLAM does not own; None without a pose."""
    if result.status != TRACKING or result.centre is None or result.rotation is None:
        return None
    owned = slam.owned_ids
    ids, pixels = frame.measurements.ids, frame.measurements.pixels
    free = np.flatnonzero([int(i) not in owned for i in ids])
    chosen = free[np.argsort(ids[free], kind='stable')[:count]]
    return FrameInput(
        frame.measurements.stamp_ns,
        result.rotation,
        result.centre,
        ids[chosen],
        pixels[chosen],
        result.pose_covariance,
        tuple(result.pose_cross_stamps),
        result.pose_cross_covariances,
    )


def filters_of(args: argparse.Namespace, target: InitTarget, map_features: int) -> PipelineConfig:
    """Return both filters' settings for a map of ``map_features``: SLAM fed the static
    features (``initialize='all'``) and told the tracker's offsets (``--tracking-offset-px``),
    the Shadow filter with its defaults (white noise, as in the node graph)."""
    slam = MonoSlamConfig(
        known_points=target_known_points(target),
        initialize='all',
        max_features=map_features,
        target_measured=map_features,
        tracking_offset_px=args.tracking_offset_px,
    )
    return PipelineConfig(slam, ShadowConfig())


def run_pass(
    frames: list[MeasurementFrame],
    camera: CameraModel,
    filters: PipelineConfig,
    shadow_features: int,
) -> FrameTimes:
    """Run SLAM and the Shadow filter over the frames; time the frames with the full load."""
    config = filters.slam
    slam = MonoSlam(camera, config)
    shadow = ShadowFilter(camera, filters.shadow)
    times = FrameTimes(frames=len(frames))
    gc.collect()
    for frame in frames:
        static = ~frame.moving
        measurements = dataclasses.replace(
            frame.measurements,
            ids=frame.measurements.ids[static],
            pixels=frame.measurements.pixels[static],
        )
        started = time.perf_counter()
        result = slam.process(measurements)
        slam_s = time.perf_counter() - started
        work = shadow_input(frame, slam, shadow_features, result)
        if work is None:
            continue
        started = time.perf_counter()
        shadow.process(work)
        shadow_s = time.perf_counter() - started
        map_size = sum(point.active for point in slam.map_points())
        if map_size == config.max_features and len(work.ids) == shadow_features:
            times.slam_s.append(slam_s)
            times.shadow_s.append(shadow_s)
            times.state_sizes.append(slam.state_size)
            times.rows.append(2 * (len(result.measured_ids) + result.known_points_used))
    return times


def dense_ekf_step(
    rng: np.random.Generator, state_size: int, rows: int
) -> tuple[float, FloatArray]:
    """Time one textbook dense EKF step of these sizes (module docstring); return the time
    (s) and the new state (kept so that nothing is optimized away)."""
    base = rng.standard_normal((state_size, state_size))
    covariance = base @ base.T / state_size + np.eye(state_size)
    transition = np.eye(state_size)
    transition[:CAMERA_SIZE, :CAMERA_SIZE] += 0.01 * rng.standard_normal((CAMERA_SIZE,) * 2)
    noise = np.zeros((state_size, state_size))
    noise[:CAMERA_SIZE, :CAMERA_SIZE] = 1e-4 * np.eye(CAMERA_SIZE)
    jacobian = rng.standard_normal((rows, state_size))
    pixel_noise = np.eye(rows)
    state, innovation = rng.standard_normal(state_size), rng.standard_normal(rows)
    identity = np.eye(state_size)
    started = time.perf_counter()
    covariance = transition @ covariance @ transition.T + noise
    gain_base = covariance @ jacobian.T
    innovation_cov = jacobian @ gain_base + pixel_noise
    gain = np.linalg.solve(innovation_cov, gain_base.T).T
    factor = identity - gain @ jacobian
    covariance = factor @ covariance @ factor.T + gain @ pixel_noise @ gain.T
    state = state + gain @ innovation
    return time.perf_counter() - started, state


def reference_times(times: FrameTimes, seed: int) -> list[float]:
    """The dense reference step per counted frame, at that frame's sizes."""
    rng = np.random.default_rng(seed)
    return [
        dense_ekf_step(rng, n, m)[0] for n, m in zip(times.state_sizes, times.rows, strict=True)
    ]


def measure(
    frames: list[MeasurementFrame],
    camera: CameraModel,
    filters: PipelineConfig,
    shadow_features: int,
    repeats: int,
    seed: int,
) -> dict[str, Any]:
    """Best of ``repeats`` passes (by median SLAM + Shadow time), each pass timing ours and
    the reference once, so that load from elsewhere falls on both alike."""
    best: dict[str, Any] | None = None
    for index in range(max(repeats, 1)):
        times = run_pass(frames, camera, filters, shadow_features)
        if not times.slam_s:
            raise RuntimeError(
                f'no frame had the full load ({filters.slam.max_features} map features and '
                f'{shadow_features} Shadow features); try a longer --duration-s'
            )
        reference = np.asarray(reference_times(times, seed + index))
        row = {
            'counted_frames': len(times.slam_s),
            'frames': times.frames,
            'state_size_median': float(np.median(times.state_sizes)),
            'measurement_rows_median': float(np.median(times.rows)),
            'slam_ms_median': 1e3 * float(np.median(times.slam_s)),
            'slam_ms_p95': 1e3 * float(np.percentile(times.slam_s, 95)),
            'shadow_ms_median': 1e3 * float(np.median(times.shadow_s)),
            'shadow_ms_p95': 1e3 * float(np.percentile(times.shadow_s, 95)),
            'total_ms_median': 1e3 * float(np.median(times.total_s)),
            'total_ms_p95': 1e3 * float(np.percentile(times.total_s, 95)),
            'reference_ms_median': 1e3 * float(np.median(reference)),
            'reference_ms_p95': 1e3 * float(np.percentile(reference, 95)),
        }
        if best is None or row['total_ms_median'] < best['total_ms_median']:
            best = row
    assert best is not None  # repeats >= 1
    best['hz'] = 1e3 / best['total_ms_median']
    best['hz_p95'] = 1e3 / best['total_ms_p95']
    best['slam_over_reference'] = best['slam_ms_median'] / best['reference_ms_median']
    return best


def render_report(result: dict[str, Any]) -> str:
    """Return the Markdown report of ``result`` (the JSON content)."""
    meta, row = result['meta'], result['timing']
    verdict = 'PASS' if row['hz'] >= ACCEPT_HZ else 'FAIL'
    goal = 'reached' if row['hz'] >= GOAL_HZ else 'not reached'
    setup = (
        f'{meta["date"]}; {meta["platform"]}, {meta["cpus"]} CPUs, pinned to '
        f'{meta["pinned"]}, Python {meta["python"]}, numpy {meta["numpy"]}; commit '
        f'{meta["commit"]}. Fig. 5 scene seed {meta["seed"]}, {meta["duration_s"]:g} s '
        f'({row["frames"]} frames at 30 Hz); {row["counted_frames"]} frames with the full '
        f'load ({meta["map_features"]} map features, {meta["shadow_features"]} Shadow '
        f'features) counted; tracker offsets {meta["tracking_offset_px"]:g} px; best of '
        f'{meta["repeats"]} passes.'
    )
    slam = (
        f'MonoSlam.process (state {row["state_size_median"]:.0f}, '
        f'{row["measurement_rows_median"]:.0f} measurement rows)'
    )
    table = [
        (slam, row['slam_ms_median'], row['slam_ms_p95']),
        ('ShadowFilter.process', row['shadow_ms_median'], row['shadow_ms_p95']),
        ('**SLAM + Shadow**', row['total_ms_median'], row['total_ms_p95']),
        (
            'reference: dense textbook EKF step, same sizes',
            row['reference_ms_median'],
            row['reference_ms_p95'],
        ),
    ]
    lines = ['# MonoSLAM EKF + Shadow filter: frames per second on one core', '', setup, '']
    lines += ['| part | ms/frame median | p95 |', '|---|---:|---:|']
    lines += [f'| {name} | {median:.2f} | {p95:.2f} |' for name, median, p95 in table]
    lines += [
        '',
        f'MonoSlam.process / reference: **{row["slam_over_reference"]:.2f}** (the '
        'measurement model, its Jacobians, gating, map management and the result, against '
        'the linear algebra alone).',
        '',
        f'Acceptance: at least {ACCEPT_HZ:.0f} frames/s: {row["hz"]:.0f} frames/s at the '
        f'median ({row["hz_p95"]:.0f} at the 95th percentile) -> **{verdict}**; the goal of '
        f'{GOAL_HZ:.0f} frames/s is {goal}.',
        '',
    ]
    return '\n'.join(lines)


SWEEP_ACCEPT_FEATURES = 100


def map_sweep(
    args: argparse.Namespace,
    sizes: list[int],
    pinned: str,
    run: Any,
    frames: list[MeasurementFrame],
    target: InitTarget,
) -> int:
    """Time SLAM (and the Shadow filter) at each map size; write the sweep report; return 0
    if SLAM keeps 30 frames/s at SWEEP_ACCEPT_FEATURES features in the state."""
    rows: list[dict[str, Any]] = []
    for size in sizes:
        filters = filters_of(args, target, size)
        print(f'map {size}: timing {len(frames)} frames x {args.repeats} passes ...', flush=True)
        try:
            timing = measure(
                frames, camera_model(run), filters, args.shadow_features, args.repeats, args.seed
            )
        except RuntimeError as error:
            rows.append({'map_features': size, 'error': str(error)})
            continue
        rows.append({'map_features': size, **timing})
    meta = {
        **run_meta(pinned),
        'seed': args.seed,
        'duration_s': args.duration_s,
        'repeats': args.repeats,
        'shadow_features': args.shadow_features,
        'tracking_offset_px': args.tracking_offset_px,
    }
    at_accept = [
        r for r in rows if r['map_features'] == SWEEP_ACCEPT_FEATURES and 'error' not in r
    ]
    slam_hz = 1e3 / at_accept[0]['slam_ms_median'] if at_accept else math.nan
    verdict = 'PASS' if slam_hz >= ACCEPT_HZ else 'FAIL'
    lines = [
        '# MonoSLAM: time per frame against the map size (one core)',
        '',
        f'{meta["date"]}; {meta["platform"]}, {meta["cpus"]} CPUs, pinned to {meta["pinned"]}, '
        f'Python {meta["python"]}, numpy {meta["numpy"]}; commit {meta["commit"]}. Fig. 5 '
        f'scene seed {args.seed}, {args.duration_s:g} s; every feature in the state measured '
        f'in each counted frame (the worst case); {args.shadow_features} Shadow features; '
        f'tracker offsets {args.tracking_offset_px:g} px; best of {args.repeats} passes.',
        '',
        '| features in state | state size | rows | SLAM ms median | p95 | SLAM Hz | '
        'SLAM + Shadow Hz | reference ms | SLAM / reference |',
        '|---:|---:|---:|---:|---:|---:|---:|---:|---:|',
    ]
    for row in rows:
        if 'error' in row:
            lines.append(f'| {row["map_features"]} | not reached: {row["error"]} |||||||| ')
            continue
        lines.append(
            f'| {row["map_features"]} | {row["state_size_median"]:.0f} | '
            f'{row["measurement_rows_median"]:.0f} | {row["slam_ms_median"]:.2f} | '
            f'{row["slam_ms_p95"]:.2f} | {1e3 / row["slam_ms_median"]:.0f} | {row["hz"]:.0f} | '
            f'{row["reference_ms_median"]:.2f} | {row["slam_over_reference"]:.2f} |'
        )
    lines += [
        '',
        f'Acceptance: MonoSlam.process at least {ACCEPT_HZ:.0f} frames/s with '
        f'{SWEEP_ACCEPT_FEATURES} features in the state: {slam_hz:.0f} frames/s -> '
        f'**{verdict}**.',
        '',
    ]
    report = '\n'.join(lines)
    output = args.output.with_name('monoslam_map_sweep.md')
    output.parent.mkdir(parents=True, exist_ok=True)
    content = {'meta': meta, 'sweep': rows}
    write_atomically(output.with_suffix('.json'), json.dumps(content, indent=2) + '\n')
    write_atomically(output, report)
    print(report)
    return 0 if verdict == 'PASS' else 1


def build_arg_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=(__doc__ or '').split('\n\n')[0])
    parser.add_argument('--seed', type=int, default=0, help='seed of the simulated run')
    parser.add_argument('--duration-s', type=float, default=20.0, help='run length, s')
    parser.add_argument('--repeats', type=int, default=3, help='timed passes')
    parser.add_argument('--map-features', type=int, default=30, help='SLAM map size')
    parser.add_argument('--shadow-features', type=int, default=20, help='Shadow features')
    parser.add_argument(
        '--map-sweep',
        default=None,
        help='comma list of map sizes to time SLAM at, e.g. 25,50,75,100,125,150',
    )
    parser.add_argument(
        '--tracking-offset-px',
        type=float,
        default=drift_bounded_offset_px(TrackerConfig().max_drift_px),
        help="the tracker's offsets that persist, declared to SLAM (each feature takes 2 "
        "more states); default: the feature tracker's, as the node graph declares them; "
        '0: white noise',
    )
    parser.add_argument('--cpu', type=int, default=None, help='CPU to pin to (default: last)')
    parser.add_argument(
        '--output', type=Path, default=DEFAULT_OUTPUT, help='Markdown report (JSON next to it)'
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_arg_parser().parse_args(argv)
    if args.duration_s <= 0 or args.repeats < 1 or args.map_features < 1:
        print('--duration-s, --repeats and --map-features must be positive', file=sys.stderr)
        return 2
    pinned = pin_to_one_core(args.cpu)
    scene = DynamicSceneConfig(duration_s=args.duration_s, objects=8, points_per_object=8)
    run = simulate_dynamic_scene(args.seed, scene)
    target = InitTarget()
    frames = simulation_frames(run, target, rng=np.random.default_rng(args.seed))
    if args.map_sweep is not None:
        try:
            sizes = [int(part) for part in args.map_sweep.split(',') if part.strip()]
        except ValueError:
            sizes = []
        if not sizes or min(sizes) < 1:
            print(f'--map-sweep {args.map_sweep!r}: a comma list of sizes >= 1', file=sys.stderr)
            return 2
        return map_sweep(args, sizes, pinned, run, frames, target)
    filters = filters_of(args, target, args.map_features)
    print(f'timing {len(frames)} frames x {args.repeats} passes ...', flush=True)
    timing = measure(
        frames, camera_model(run), filters, args.shadow_features, args.repeats, args.seed
    )
    result: dict[str, Any] = {
        'meta': {
            **run_meta(pinned),
            'seed': args.seed,
            'duration_s': args.duration_s,
            'repeats': args.repeats,
            'map_features': args.map_features,
            'shadow_features': args.shadow_features,
            'tracking_offset_px': args.tracking_offset_px,
        },
        'timing': timing,
    }
    report = render_report(result)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(args.output.with_suffix('.json'), json.dumps(result, indent=2) + '\n')
    write_atomically(args.output, report)
    print(report)
    return 0 if timing['hz'] >= ACCEPT_HZ else 1


if __name__ == '__main__':
    sys.exit(main())
