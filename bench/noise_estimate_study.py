"""Study: the tracking-noise estimator (``noise_estimate``) on MonoSLAM's own residuals.

Paper 001's Fig. 5 scene (``monoslam_evaluate``'s simulation: 200 static points, 8 objects x 8
moving points, 30 Hz, the target's corners as known points) runs through the ROS-free
pipeline's variant (a) (``monoslam_pipeline.run_variant``: MonoSLAM fed the static features)
with nothing declared about the tracker: SLAM is told white 1 px noise and no offsets, as a
user who knows nothing would run it. Two tracker noises are simulated:

* ``white``: white 1 px per axis;
* ``offsets``: white 1 px plus per-track offsets of 2 px (``tracking_offset_px``), correlation
  time 1 s, re-anchoring jumps with probability 0.02 per frame: effective correlation time
  0.62 s (``DynamicSceneConfig.tracking_correlation_time_s``).

Each frame, around SLAM's step (``attach`` wraps the processor's ``process_frame``), the
residuals of the features SLAM measured (``MonoSlamResult.measured_ids``) are computed from
public state and fed to one estimator per column:

* ``measured``: z - h(x+), h(x+) from ``MonoSlam.predictions`` at the frame's own stamp (the
  updated state): what MonoSLAM -> Shadow filter would feed;
* ``established``: the same, for features measured in ``--established`` earlier frames;
* ``innovation``: z - h(x-), ``MonoSlam.predictions`` before the step;
* ``observed``: z - h(x+) of the measured and the rejected features in SLAM's state;
* ``true_points``: z minus the true point seen from SLAM's camera (a diagnostic: the error
  the map's points absorb is back in);
* ``true_measured``: the measured features' true tracking error (pixel - true projection):
  the estimator with a perfect filter, on the features SLAM's gate let through;
* ``true_all``: every static feature's true tracking error: the estimator alone;
* ``batch``: after the run, each track fed to SLAM with at least ``BATCH_MIN_VIEWS``
  sightings in tracking frames is triangulated over all of them with SLAM's poses
  (``noise_monitor.batch_residuals``), and its sightings' residuals against that fixed
  point are fed in time order: neither SLAM's gate nor its moving point estimate touches
  them (a point fixed over the track absorbs only its mean offset, which the variogram
  cancels anyway).

The first table lists per setting and seed the truth and each estimate as white / offset /
tau (px, px, s; "(prior)": not confident), and from when the ``measured`` and ``true_all``
estimates were usable: confident and, from then on, within 20 % of their final white and
marginal sigma; the second, those two estimates over time. ``--out`` also writes both.

Run (after ``bash scripts/bootstrap.sh``; about 3 min on one core with the defaults)::

    source scripts/env.sh
    python bench/noise_estimate_study.py [--seeds 0,1,2] [--duration-s 60] [--out FILE]
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_types import (
    TRACKING,
    MonoSlamConfig,
    MonoSlamFrame,
)
from monoslam_shadow_node.monoslam.core.noise_estimate import NoiseEstimate, TrackingNoiseEstimator
from monoslam_shadow_node.monoslam.core.noise_monitor import batch_residuals
from monoslam_shadow_node.monoslam.processor import MonoSlamProcessor, MonoSlamStep
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_evaluation.monoslam_pipeline import (
    PipelineConfig,
    run_variant,
    simulation_frames,
    target_known_points,
)
from slam_evaluation.monoslam_runs import TARGET_NOISE_SEED_OFFSET, Settings
from slam_evaluation.shadow_runs import camera_model
from slam_sim.core.dynamic_scene import DynamicSceneRun, FeatureFrame, simulate_dynamic_scene

SETTINGS = {'white': (0.0, 0.0), 'offsets': (2.0, 0.02)}  # offset px, jump probability
COLUMNS = ('measured', 'established', 'innovation', 'observed', 'true_points',
           'true_measured', 'true_all', 'batch')  # fmt: skip
BATCH_MIN_VIEWS = 10
TIMED = ('measured', 'true_all')
STABLE_FRACTION = 0.2


TrackedFrame = tuple[int, FloatArray, FloatArray, IntArray, FloatArray]
"""A frame SLAM tracked: stamp ns, camera centre (3,), T_world_camera rotation (3, 3), every
feature's id (N,) and pixel (N, 2)."""


@dataclass
class _Feed:
    """One run's estimators, the measured count per feature and the TIMED estimates each
    second of the run ((s, estimate) lists)."""

    run: DynamicSceneRun
    established_after: int
    estimators: dict[str, TrackingNoiseEstimator] = field(
        default_factory=lambda: {name: TrackingNoiseEstimator() for name in COLUMNS}
    )
    measured_count: dict[int, int] = field(default_factory=dict)
    tracked: list[TrackedFrame] = field(default_factory=list)
    history: dict[str, list[tuple[float, NoiseEstimate]]] = field(default_factory=dict)
    next_report_ns: int = 0


def _rows(ids: IntArray, wanted: IntArray) -> IntArray:
    """Return the rows of ``ids`` (N,) holding ``wanted`` (M,), each of which is in ids."""
    order = np.argsort(ids)
    return np.asarray(order[np.searchsorted(ids, wanted, sorter=order)], dtype=np.int64)


def _attach(feed: _Feed) -> Callable[[MonoSlamProcessor], None]:
    """Return the ``run_variant`` hook that wraps the SLAM processor's frame step."""
    truth = {frame.stamp_ns: frame for frame in feed.run.frames}
    start_ns = feed.run.frames[0].stamp_ns
    feed.next_report_ns = start_ns + 10**9

    def attach(processor: MonoSlamProcessor) -> None:
        step_frame = processor.process_frame

        def process_frame(frame: MonoSlamFrame, frame_id: str = '') -> MonoSlamStep:
            before = None
            if processor.slam is not None:
                before = processor.slam.predictions(frame.stamp_ns, frame.ids.tolist())[:2]
            step = step_frame(frame, frame_id)
            _feed_frame(processor, frame, step, before, truth[frame.stamp_ns], feed)
            if frame.stamp_ns >= feed.next_report_ns:
                elapsed_s = (frame.stamp_ns - start_ns) * 1e-9
                for name in TIMED:
                    estimate = feed.estimators[name].estimate()
                    feed.history.setdefault(name, []).append((elapsed_s, estimate))
                feed.next_report_ns += 10**9
            return step

        setattr(processor, 'process_frame', process_frame)  # noqa: B010 (wraps a method)

    return attach


def _feed_frame(
    processor: MonoSlamProcessor,
    frame: MonoSlamFrame,
    step: MonoSlamStep,
    before: tuple[IntArray, FloatArray] | None,
    truth: FeatureFrame,
    feed: _Feed,
) -> None:
    """Feed one frame's residuals (module docstring) to the estimators."""
    result, slam, add = step.result, processor.slam, feed.estimators
    if result.status != TRACKING or slam is None or not result.measured_ids:
        return
    stamp_ns = frame.stamp_ns
    in_state = sorted(set(result.measured_ids) | set(result.rejected_ids))
    ids, predicted, _, _ = slam.predictions(stamp_ns, in_state)
    residuals = frame.pixels[_rows(frame.ids, ids)] - predicted
    add['observed'].add(stamp_ns, ids, residuals)
    measured = np.isin(ids, result.measured_ids)
    ids, residuals = ids[measured], residuals[measured]
    add['measured'].add(stamp_ns, ids, residuals)
    old = np.array([feed.measured_count.get(i, 0) >= feed.established_after for i in ids.tolist()])
    add['established'].add(stamp_ns, ids[old], residuals[old])
    for i in ids.tolist():
        feed.measured_count[i] = feed.measured_count.get(i, 0) + 1
    if before is not None:
        before_ids, before_pixels = before
        used = np.isin(before_ids, ids)
        innovations = frame.pixels[_rows(frame.ids, before_ids[used])] - before_pixels[used]
        add['innovation'].add(stamp_ns, before_ids[used], innovations)
    rows = _rows(truth.track_ids, ids)
    add['true_measured'].add(stamp_ns, ids, truth.pixels[rows] - truth.true_pixels[rows])
    assert result.centre is not None and result.rotation is not None
    feed.tracked.append((stamp_ns, result.centre, result.rotation, frame.ids, frame.pixels))
    points = feed.run.point_positions[0][[feed.run.track_point[i] for i in ids.tolist()]]
    seen = slam.camera.project((points - result.centre) @ result.rotation)
    add['true_points'].add(stamp_ns, ids, frame.pixels[_rows(frame.ids, ids)] - seen)
    static = np.isin(truth.track_ids, frame.ids)
    add['true_all'].add(
        stamp_ns, truth.track_ids[static], (truth.pixels - truth.true_pixels)[static]
    )


def feed_fixed_points(
    estimator: TrackingNoiseEstimator,
    frames: list[TrackedFrame],
    camera: CameraModel,
    keep: set[int] | None = None,
    cache: dict[int, tuple[int, IntArray, FloatArray]] | None = None,
) -> None:
    """Feed ``estimator``, in time order, the residuals of every track (of ``keep``, None:
    all) with at least ``BATCH_MIN_VIEWS`` sightings in ``frames``, each against its point
    fixed over them (``noise_monitor.batch_residuals``); ``cache`` keeps a track's fit until it
    gains sightings."""
    sightings: dict[int, list[tuple[int, FloatArray]]] = {}
    for row, (_, _, _, ids, pixels) in enumerate(frames):
        for track_id, pixel in zip(ids.tolist(), pixels, strict=True):
            if keep is None or track_id in keep:
                sightings.setdefault(track_id, []).append((row, pixel))
    centres = np.array([c for _, c, _, _, _ in frames])
    rotations = np.array([r for _, _, r, _, _ in frames])
    cache = {} if cache is None else cache
    by_row: dict[int, list[tuple[int, FloatArray]]] = {}
    for track_id, seen in sightings.items():
        if len(seen) < BATCH_MIN_VIEWS:
            continue
        fitted = cache.get(track_id)
        if fitted is None or fitted[0] != len(seen):
            rows = np.array([row for row, _ in seen])
            pixels = np.array([pixel for _, pixel in seen])
            fitted = (
                len(seen),
                rows,
                batch_residuals(camera, centres[rows], rotations[rows], pixels),
            )
            cache[track_id] = fitted
        for row, residual in zip(fitted[1].tolist(), fitted[2], strict=True):
            if np.all(np.isfinite(residual)):  # NaN: no ray, or the point behind the camera
                by_row.setdefault(row, []).append((track_id, residual))
    for row in sorted(by_row):
        ids = np.array([track_id for track_id, _ in by_row[row]], dtype=np.int64)
        estimator.add(frames[row][0], ids, np.array([residual for _, residual in by_row[row]]))


def usable_after_s(history: list[tuple[float, NoiseEstimate]]) -> float:
    """Return the time (s) from which the estimate is confident and its white and marginal
    sigma stay within ``STABLE_FRACTION`` of the final ones (NaN: never)."""
    if not history or not history[-1][1].confident:
        return math.nan
    final = history[-1][1]
    final_marginal = math.hypot(final.white_px, final.offset_px)
    since = math.nan
    for elapsed_s, estimate in history:
        marginal = math.hypot(estimate.white_px, estimate.offset_px)
        good = (
            estimate.confident
            and abs(estimate.white_px / final.white_px - 1.0) <= STABLE_FRACTION
            and abs(marginal / final_marginal - 1.0) <= STABLE_FRACTION
        )
        if not good:
            since = math.nan
        elif math.isnan(since):
            since = elapsed_s
    return since


@dataclass(frozen=True)
class StudyRow:
    """One run: setting, seed, true white / offset / tau, the estimates per column, when
    the TIMED ones became usable (s) and their estimates each second, tracking losses and
    wall time (s)."""

    setting: str
    seed: int
    truth: tuple[float, float, float]
    estimates: dict[str, NoiseEstimate]
    usable_s: dict[str, float]
    history: dict[str, list[tuple[float, NoiseEstimate]]]
    lost: int
    wall_s: float


def study_run(setting: str, seed: int, duration_s: float, established: int) -> StudyRow:
    """Run variant (a) on one seed and setting; return the truth and the estimates."""
    offset_px, jump = SETTINGS[setting]
    settings = Settings(
        seeds=(seed,), duration_s=duration_s, variants=('a',), out=Path(),
        tracking_offset_px=offset_px, tracking_jump_probability=jump,
    )  # fmt: skip
    scene = settings.scene()
    run = simulate_dynamic_scene(seed, scene)
    markers = settings.markers()
    rng = np.random.default_rng(TARGET_NOISE_SEED_OFFSET + seed)
    frames = simulation_frames(run, markers, rng=rng)
    # nothing declared: SLAM is told white 1 px (its default), no offsets, and takes no estimate
    config = PipelineConfig(
        MonoSlamConfig(known_points=target_known_points(markers), estimate_noise=False)
    )
    feed = _Feed(run, established)
    started = time.perf_counter()
    record = run_variant('a', frames, camera_model(run), config, attach=_attach(feed))
    feed_fixed_points(feed.estimators['batch'], feed.tracked, camera_model(run))
    tau_s = scene.tracking_correlation_time_s if offset_px > 0.0 else math.nan
    return StudyRow(
        setting,
        seed,
        (scene.pixel_noise_px, offset_px, tau_s),
        {name: estimator.estimate() for name, estimator in feed.estimators.items()},
        {name: usable_after_s(feed.history.get(name, [])) for name in TIMED},
        feed.history,
        len(record.lost_frames),
        time.perf_counter() - started,
    )


def _cell(estimate: NoiseEstimate) -> str:
    mark = '' if estimate.confident else ' (prior)'
    return (
        f'{estimate.white_px:.2f} / {estimate.offset_px:.2f} / {estimate.offset_time_s:.2f}{mark}'
    )


def table(rows: list[StudyRow]) -> str:
    """Return the Markdown table of the runs."""
    head = ['setting', 'seed', 'truth', *COLUMNS, *(f'{n} usable after s' for n in TIMED)]
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for row in rows:
        white, offset, tau = row.truth
        cells = [row.setting, str(row.seed), f'{white:.2f} / {offset:.2f} / {tau:.2f}']
        cells += [_cell(row.estimates[name]) for name in COLUMNS]
        cells += [f'{row.usable_s[name]:.0f}' for name in TIMED]
        lines.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def convergence(rows: list[StudyRow], times_s: tuple[float, ...] = (2, 5, 10, 20, 40)) -> str:
    """Return the Markdown table of each run's TIMED estimates at ``times_s`` (s) and at the
    end."""
    head = ['setting', 'seed', 'estimator', *(f'{t:g} s' for t in times_s), 'end']
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for row in rows:
        for name in TIMED:
            history = row.history.get(name, [])
            cells = [row.setting, str(row.seed), name]
            for wanted_s in times_s:
                at = [estimate for elapsed_s, estimate in history if elapsed_s <= wanted_s + 0.5]
                cells.append(_cell(at[-1]) if at else '-')
            cells.append(_cell(history[-1][1]) if history else '-')
            lines.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def main() -> None:
    """Run the study (module docstring) and print its table."""
    parser = argparse.ArgumentParser(description=(__doc__ or '').split('\n', 1)[0])
    parser.add_argument('--seeds', default='0,1,2', help='comma-separated seeds (0,1,2)')
    parser.add_argument('--duration-s', type=float, default=60.0, help='run length (60 s)')
    parser.add_argument('--settings', default=','.join(SETTINGS), help='white,offsets')
    parser.add_argument(
        '--established', type=int, default=30, help='earlier measurements that make it old (30)'
    )
    parser.add_argument('--out', type=Path, help='also write the table (Markdown) here')
    args = parser.parse_args()
    rows = []
    for setting in args.settings.split(','):
        for seed in (int(s) for s in args.seeds.split(',')):
            row = study_run(setting, seed, args.duration_s, args.established)
            rows.append(row)
            print(f'{setting} seed {seed}: {row.wall_s:.0f} s, lost {row.lost}', flush=True)
    text = table(rows) + '\n\nConvergence (white / offset / tau):\n\n' + convergence(rows)
    print(text)
    if args.out is not None:
        args.out.write_text(text + '\n')


if __name__ == '__main__':
    main()
