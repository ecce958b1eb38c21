"""Benchmark: Shadow filter speed on one core, next to compiled per-feature references.

Inputs come from one simulated run (``slam_sim.core.dynamic_scene.simulate_dynamic_scene``:
a hand-held camera in a room, ~175 tracked features per frame at 30 Hz, 1 px pixel noise,
24 of the 224 points on 4 moving objects). Measured in the same run, pinned to one CPU
(``sched_setaffinity``) with cv2.setNumThreads(1):

* EKF feature updates/s: ``shadow_ekf.predict`` + ``update`` of N features per frame at once,
  as the filter batches them, over a window of frames in which all N tracks are seen; next
  to two references over the same pixels: N ``cv2.KalmanFilter`` objects (6 states, 2-D
  measurement, C++), ``predict`` + ``correct`` each per frame in a Python loop, and the same
  EKF called one feature at a time (N = 1 arrays in a Python loop);
* ``ShadowFilter.process`` end to end over the whole run (prediction, update, new tracks,
  classification, handovers, reports), with known poses and with a pose covariance;
* one three-ray test (``rays.three_ray_test``) per call, median and 95th percentile, on
  triples of views of simulated tracks chosen as the filter chooses them, with and without
  the motion-visibility point and the pose covariance; next to a minimal compiled check:
  ``cv2.triangulatePoints`` from the outer views, reprojection into all three and a
  chi-square on the reprojection error. For information, the filter's second test per
  classification round (``static_fit.motion_score_test`` over all views of the track) on the
  same tracks.

Acceptance (the issue): at least 1000 Shadow-filter feature updates per second (the slowest
of the EKF at every N and of ``process`` end to end) and one three-ray test in at most
0.2 ms (median of the call as ``ShadowFilter`` makes it, the slower of known poses and pose
covariance). PASS or FAIL is printed; FAIL exits with 1. Results go to
``bench/results/shadow_filter_speed.md`` and ``.json``.

Run (after ``bash scripts/bootstrap.sh``)::

    source scripts/env.sh
    python bench/shadow_filter_speed.py [--repeats 5] [--seed 0]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import itertools
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, TypeVar
from unittest import mock

import cv2
import numpy as np
from bench_common import best_of, pin_to_one_core, run_meta

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, STATIC
from monoslam_shadow_node.common.core.projective import chi2_quantile
from monoslam_shadow_node.shadow_filter.core import shadow_decision as shadow_decision_module
from monoslam_shadow_node.shadow_filter.core import shadow_filter as shadow_filter_module
from monoslam_shadow_node.shadow_filter.core.rays import (
    View,
    pixel_ray_directions,
    ray_angle,
    three_ray_test,
)
from monoslam_shadow_node.shadow_filter.core.shadow_classifier import ClassifierConfig
from monoslam_shadow_node.shadow_filter.core.shadow_ekf import (
    EkfConfig,
    initial_states,
    predict,
    update,
)
from monoslam_shadow_node.shadow_filter.core.shadow_filter import FrameInput, ShadowFilter
from monoslam_shadow_node.shadow_filter.core.static_fit import motion_score_test
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.files import write_atomically
from slam_sim.core.dynamic_scene import DynamicSceneRun, simulate_dynamic_scene

S = TypeVar('S')
T = TypeVar('T')

BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / 'results' / 'shadow_filter_speed.md'
ACCEPT_UPDATES_PER_S = 1000.0
ACCEPT_TEST_MS = 0.2
FEATURE_COUNTS = (10, 20, 50, 150)
POSE_COVARIANCE = np.diag([0.01**2] * 3 + [0.005**2] * 3)  # 1 cm, 0.29 deg per axis
EKF = EkfConfig()
CLASSIFIER = ClassifierConfig()


def best_prepared(
    repeats: int, prepare: Callable[[], S], work: Callable[[S], T]
) -> tuple[float, T]:
    """Return the shortest wall time (s) of ``work(prepare())`` over the passes (``prepare``
    untimed) and the result of the fastest pass."""
    best, result = float('inf'), None
    for _ in range(max(repeats, 1)):
        state = prepare()
        gc.collect()
        started = time.perf_counter()
        output = work(state)
        elapsed = time.perf_counter() - started
        if elapsed < best:
            best, result = elapsed, output
    assert result is not None
    return best, result


def camera_of(run: DynamicSceneRun) -> CameraModel:
    """Return the run's camera (plumb_bob) as the Shadow filter's camera model."""
    info = run.camera.camera_info()
    return CameraModel(info.width, info.height, info.k.reshape(3, 3), info.d)


# --- EKF feature updates ---------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class EkfWorkload:
    """N features through F frames: first pixels (N, 2), start states (N, 7) and covariances
    (N, 7, 7) in the first camera frame, per step the motion into the next camera frame
    (F-1, 3, 3) and (F-1, 3) m, the step dt_s and the measured pixels (F-1, N, 2)."""

    first_pixels: FloatArray
    states: FloatArray
    covariances: FloatArray
    rotations: FloatArray
    translations: FloatArray
    dt_s: float
    pixels: FloatArray


def persistent_tracks(run: DynamicSceneRun, frames: int) -> tuple[int, list[int]]:
    """Return the start of the ``frames``-long window in which most tracks are seen in every
    frame, and those track ids."""
    seen = [set(frame.track_ids.tolist()) for frame in run.frames]
    best: tuple[int, set[int]] = (0, set())
    for start in range(0, len(seen) - frames + 1, 5):
        common = set.intersection(*seen[start : start + frames])
        if len(common) > len(best[1]):
            best = (start, common)
    return best[0], sorted(best[1])


def ekf_workload(
    run: DynamicSceneRun, camera: CameraModel, start: int, frames: int, ids: FloatArray
) -> EkfWorkload:
    """Return the workload of tracks ``ids`` over ``frames`` frames from ``start``."""
    window = run.frames[start : start + frames]
    pixels = np.array([f.pixels[np.searchsorted(f.track_ids, ids)] for f in window])
    rays, jacobians = camera.pixel_rays(pixels[0])
    directions, covariances, _ = pixel_ray_directions(
        rays, jacobians, np.eye(3), EKF.pixel_sigma_px
    )
    states, covariances = initial_states(directions, covariances, EKF)
    rotations, translations = [], []
    for before, after in itertools.pairwise(window):
        rotation = after.camera_rotation.T
        rotations.append(rotation @ before.camera_rotation)
        translations.append(rotation @ (before.camera_position - after.camera_position))
    return EkfWorkload(
        pixels[0], states, covariances, np.array(rotations), np.array(translations),
        1.0 / run.config.rate_hz, pixels[1:],
    )  # fmt: skip


def run_batched(work: EkfWorkload, camera: CameraModel) -> FloatArray:
    """Return the states (N, 7) after all steps, all features per call (as the filter)."""
    states, covariances = work.states, work.covariances
    for k in range(len(work.pixels)):
        states, covariances = predict(
            states, covariances, work.rotations[k], work.translations[k], work.dt_s, EKF
        )
        result = update(states, covariances, work.pixels[k], camera, EKF)
        states, covariances = result.states, result.covariances
    return states


def run_per_feature(work: EkfWorkload, camera: CameraModel) -> FloatArray:
    """Return the states (N, 7) after all steps, the same EKF called one feature at a time."""
    states = [work.states[i : i + 1] for i in range(len(work.states))]
    covariances = [work.covariances[i : i + 1] for i in range(len(work.states))]
    for k in range(len(work.pixels)):
        rotation, translation, pixels = work.rotations[k], work.translations[k], work.pixels[k]
        for i in range(len(states)):
            state, covariance = predict(
                states[i], covariances[i], rotation, translation, work.dt_s, EKF
            )
            result = update(state, covariance, pixels[i : i + 1], camera, EKF)
            states[i], covariances[i] = result.states, result.covariances
    return np.concatenate(states)


def kalman_filters(work: EkfWorkload) -> list[Any]:
    """Return one cv2.KalmanFilter per feature: state (u, v, u', v', u'', v'') px, constant
    acceleration with white jerk, measurement (u, v) px with the pixel noise."""
    dt, eye = work.dt_s, np.eye(2)
    transition = np.block(
        [[eye, dt * eye, 0.5 * dt * dt * eye], [0 * eye, eye, dt * eye], [0 * eye, 0 * eye, eye]]
    )
    jerk = np.array(
        [[dt**5 / 20, dt**4 / 8, dt**3 / 6], [dt**4 / 8, dt**3 / 3, dt**2 / 2],
         [dt**3 / 6, dt**2 / 2, dt]]
    )  # fmt: skip
    filters = []
    for u, v in work.first_pixels:
        kalman = cv2.KalmanFilter(6, 2, 0, cv2.CV_64F)
        kalman.transitionMatrix = transition.copy()
        kalman.measurementMatrix = np.eye(2, 6)
        kalman.processNoiseCov = 1e4 * np.kron(jerk, eye)
        kalman.measurementNoiseCov = EKF.pixel_sigma_px**2 * eye
        kalman.statePost = np.array([[u], [v], [0.0], [0.0], [0.0], [0.0]])
        kalman.errorCovPost = np.diag([1.0, 1.0, 1e4, 1e4, 1e6, 1e6])
        filters.append(kalman)
    return filters


def run_kalman(work: EkfWorkload, filters: list[Any]) -> FloatArray:
    """Return the filters' states (N, 6) after predict + correct per feature and frame."""
    columns = work.pixels[:, :, :, None].copy()  # (F-1, N, 2, 1), as cv2 takes measurements
    for k in range(len(columns)):
        for kalman, measured in zip(filters, columns[k], strict=True):
            kalman.predict()
            kalman.correct(measured)
    return np.array([kalman.statePost[:, 0] for kalman in filters])


def measure_ekf(
    run: DynamicSceneRun, camera: CameraModel, frames: int, repeats: int, seed: int
) -> list[dict[str, Any]]:
    """Return one row per N of FEATURE_COUNTS: updates/s of ours and the references."""
    start, persistent = persistent_tracks(run, frames)
    if len(persistent) < max(FEATURE_COUNTS):
        raise ValueError(
            f'only {len(persistent)} tracks are seen in all of {frames} frames; '
            f'{max(FEATURE_COUNTS)} are needed: lower --ekf-frames'
        )
    chosen = np.random.default_rng(seed).permutation(persistent)
    rows = []
    for count in FEATURE_COUNTS:
        work = ekf_workload(run, camera, start, frames, np.sort(chosen[:count]))
        updates = count * len(work.pixels)
        ours_s, batched = best_of(repeats, partial(run_batched, work, camera))
        single_s, single = best_of(repeats, partial(run_per_feature, work, camera))
        kalman_s, _ = best_prepared(
            repeats, partial(kalman_filters, work), partial(run_kalman, work)
        )
        rows.append({
            'features': count,
            'frames': len(work.pixels),
            'ours_updates_per_s': updates / ours_s,
            'cv2_kalman_updates_per_s': updates / kalman_s,
            'per_feature_updates_per_s': updates / single_s,
            'per_feature_max_state_difference': float(np.max(np.abs(single - batched))),
        })  # fmt: skip
        print(
            f'EKF N={count}: ours {updates / ours_s:.0f} updates/s, cv2.KalmanFilter '
            f'{updates / kalman_s:.0f}, per feature {updates / single_s:.0f}',
            flush=True,
        )
    return rows


# --- ShadowFilter.process end to end ---------------------------------------------------------


def frame_inputs(run: DynamicSceneRun, pose_covariance: FloatArray | None) -> list[FrameInput]:
    """Return the run's frames as the filter's inputs (true poses, noisy pixels)."""
    return [
        FrameInput(f.stamp_ns, f.camera_rotation, f.camera_position, f.track_ids, f.pixels,
                   pose_covariance)
        for f in run.frames
    ]  # fmt: skip


CLASSIFIER_TESTS = {
    'three_ray_test': (shadow_decision_module, 'three_ray_tests'),
    'motion_score_test': (shadow_filter_module, 'score_tests'),
}
"""The tests ``ShadowFilter`` runs per classification round: where it looks each stage up
(module, name; each takes the round's due tests together) under the name counted. The
counting pass wraps each and counts its due tests (it fails if one is renamed)."""


def run_process(shadow: ShadowFilter, frames: list[FrameInput]) -> tuple[FloatArray, list[int]]:
    """Return the seconds each frame took (F,) and the statuses of the decisions made (the
    results are dropped: kept, they would grow the heap the garbage collector scans)."""
    seconds, statuses = np.empty(len(frames)), []
    for k, frame in enumerate(frames):
        started = time.perf_counter()
        result = shadow.process(frame)
        seconds[k] = time.perf_counter() - started
        statuses += [decision.status for decision in result.decisions]
    return seconds, statuses


def tests_in_process(
    camera: CameraModel, frames: list[FrameInput]
) -> tuple[dict[str, int], dict[str, float], float]:
    """Return the calls of each of CLASSIFIER_TESTS in one pass, the seconds spent in each
    and the pass's seconds (an extra, untimed pass with counting wrappers)."""
    calls = dict.fromkeys(CLASSIFIER_TESTS, 0)
    spent = dict.fromkeys(CLASSIFIER_TESTS, 0.0)

    def counting(name: str, function: Callable[..., Any]) -> Callable[..., Any]:
        def counted(*args: Any, **kwargs: Any) -> Any:
            started = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                spent[name] += time.perf_counter() - started
                calls[name] += len(args[0])  # the due tests of the round

        return counted

    with contextlib.ExitStack() as stack:
        for name, (module, attribute) in CLASSIFIER_TESTS.items():
            wrapper = counting(name, getattr(module, attribute))
            stack.enter_context(mock.patch.object(module, attribute, wrapper))
        seconds, _ = run_process(ShadowFilter(camera), frames)
    return calls, spent, float(np.sum(seconds))


def measure_process(
    run: DynamicSceneRun, camera: CameraModel, repeats: int
) -> list[dict[str, Any]]:
    """Return one row per pose variant: features/s and ms per frame of the whole run."""
    rows = []
    for label, covariance in (('known poses', None), ('pose covariance', POSE_COVARIANCE)):
        frames = frame_inputs(run, covariance)
        features = sum(len(frame.ids) for frame in frames)
        total_s, (seconds, statuses) = best_prepared(
            repeats, partial(ShadowFilter, camera), partial(run_process, frames=frames)
        )
        calls, spent, counted_s = tests_in_process(camera, frames)
        rows.append({
            'poses': label,
            'frames': len(frames),
            'features': features,
            'features_per_s': features / total_s,
            'ms_per_frame_median': 1e3 * float(np.median(seconds)),
            'ms_per_frame_p95': 1e3 * float(np.percentile(seconds, 95)),
            'ms_per_frame_max': 1e3 * float(np.max(seconds)),
            'three_ray_tests': calls['three_ray_test'],
            'score_tests': calls['motion_score_test'],
            'share_in_three_ray_tests': spent['three_ray_test'] / counted_s,
            'share_in_score_tests': spent['motion_score_test'] / counted_s,
            'static_decisions': statuses.count(STATIC),
            'dynamic_decisions': statuses.count(DYNAMIC),
        })  # fmt: skip
        print(f'process, {label}: {features / total_s:.0f} features/s', flush=True)
    return rows


# --- three-ray test --------------------------------------------------------------------------

Views = tuple[View, View, View]


@dataclass(frozen=True, eq=False)
class RayCase:
    """Three views of one track (first, middle, last) and all its views from the first to
    the last (as the score test gets them), each also with POSE_COVARIANCE, the point's world
    position (3,) m at the last view, whether it moves, and the reference's inputs: world ->
    normalized camera projections (3, 3, 4) and the measured normalized image coordinates
    (3, 2, 1)."""

    views: Views
    posed: Views
    track_views: list[View]
    track_posed: list[View]
    point: FloatArray
    moving: bool
    projections: FloatArray
    normalized: FloatArray


def ray_cases(run: DynamicSceneRun, camera: CameraModel, count: int, seed: int) -> list[RayCase]:
    """Return up to ``count`` triples of views from the run's tracks (a start every 15
    sightings of every track), chosen at random."""
    directions, covariances = [], []
    sightings: dict[int, list[tuple[int, int]]] = {}  # track id -> (frame index, row)
    for k, frame in enumerate(run.frames):
        rays, jacobians = camera.pixel_rays(frame.pixels)
        direction, covariance, _ = pixel_ray_directions(
            rays, jacobians, frame.camera_rotation, EKF.pixel_sigma_px
        )
        directions.append(direction)
        covariances.append(covariance)
        for row, track in enumerate(frame.track_ids.tolist()):
            sightings.setdefault(track, []).append((k, row))
    rng = np.random.default_rng(seed)
    candidates = []
    for track, seen in sightings.items():
        for first in range(0, len(seen) - 2, 15):
            target = CLASSIFIER.parallax_for_test(int(rng.integers(3)))
            case = ray_case(run, seen[first:], directions, covariances, track, target)
            if case is not None:
                candidates.append(case)
    picked = rng.choice(len(candidates), min(count, len(candidates)), replace=False)
    return [candidates[i] for i in sorted(picked)]


def ray_case(
    run: DynamicSceneRun,
    seen: list[tuple[int, int]],
    directions: list[FloatArray],
    covariances: list[FloatArray],
    track: int,
    parallax_rad: float,
) -> RayCase | None:
    """Return the test the filter would run on sightings ``seen`` (consecutive frames) once
    the true parallax reaches ``parallax_rad``: the last view one frame after the trigger, the
    middle view the one farthest from both ends; None if the track ends first."""
    point_index = run.track_point[track]
    centres = np.array([run.frames[k].camera_position for k, _ in seen])
    for trigger in range(2, len(seen) - 1):
        position = run.point_positions[seen[trigger][0], point_index]
        baseline = float(np.linalg.norm(centres[trigger] - centres[0]))
        if baseline < CLASSIFIER.min_baseline_m:
            continue
        if ray_angle(*(_unit(position - centres[i]) for i in (0, trigger))) >= parallax_rad:
            break
    else:
        return None
    last = trigger + 1
    spread = np.minimum(
        np.linalg.norm(centres[1:last] - centres[0], axis=1),
        np.linalg.norm(centres[1:last] - centres[last], axis=1),
    )
    middle = 1 + int(np.argmax(spread))
    if spread[middle - 1] < CLASSIFIER.middle_min_fraction * np.linalg.norm(
        centres[last] - centres[0]
    ):
        return None
    track_views = [
        View(k, run.frames[k].stamp_ns, run.frames[k].camera_position, directions[k][row],
             covariances[k][row])
        for k, row in seen[: last + 1]
    ]  # fmt: skip
    projections, normalized = [], []
    for k, row in (seen[0], seen[middle], seen[last]):
        rotation, centre = run.frames[k].camera_rotation, run.frames[k].camera_position
        projections.append(np.hstack([rotation.T, -(rotation.T @ centre)[:, None]]))
        ray = rotation.T @ directions[k][row]
        normalized.append(ray[:2, None] / ray[2])
    point = run.point_positions[seen[last][0], point_index]
    first, mid, end = track_views[0], track_views[middle], track_views[last]
    try:
        three_ray_test(first, mid, end, CLASSIFIER.test_alpha, point=point)
    except ValueError:
        return None
    posed = [dataclasses.replace(v, pose_covariance=POSE_COVARIANCE) for v in track_views]
    return RayCase(
        (first, mid, end), (posed[0], posed[middle], posed[last]), track_views, posed, point,
        bool(run.point_moving[point_index]), np.array(projections), np.array(normalized),
    )  # fmt: skip


def _unit(vector: FloatArray) -> FloatArray:
    return np.asarray(vector / np.linalg.norm(vector), dtype=np.float64)


def reference_rejects(case: RayCase, threshold: float) -> bool:
    """Return whether the minimal compiled check rejects the triple: the point triangulated
    from the outer views (cv2.triangulatePoints), reprojected into all three, its squared
    normalized reprojection error above ``threshold``."""
    point = cv2.triangulatePoints(
        case.projections[0], case.projections[2], case.normalized[0], case.normalized[2]
    )
    projected = case.projections @ point[:, 0]
    residual = projected[:, :2] / projected[:, 2:] - case.normalized[:, :, 0]
    return float(np.sum(residual * residual)) > threshold


def time_calls(
    function: Callable[[RayCase], bool], cases: list[RayCase], repeats: int
) -> tuple[FloatArray, FloatArray]:
    """Return the microseconds of every call, pooled over ``repeats`` passes after one
    untimed warm-up pass, and whether each case was rejected (C,)."""
    rejected = np.array([function(case) for case in cases])
    gc.collect()
    nanoseconds = []
    for _ in range(max(repeats, 1)):
        for case in cases:
            started = time.perf_counter_ns()
            function(case)
            nanoseconds.append(time.perf_counter_ns() - started)
    return 1e-3 * np.array(nanoseconds, dtype=np.float64), rejected


RAY_VARIANTS = (
    # label, pose covariance, motion-visibility point, acceptance variant. The acceptance
    # variants mirror the call in shadow_classifier.classify (no point: the motion visibility
    # comes from the score test), with known poses and with a pose covariance; update them
    # when that call changes.
    ('three_ray_test, known poses (as the filter calls it)', False, False, True),
    ('three_ray_test, known poses, with motion visibility (point)', False, True, False),
    ('three_ray_test, pose covariance (as the filter calls it)', True, False, True),
    ('three_ray_test, pose covariance, with motion visibility (point)', True, True, False),
)


def measure_rays(cases: list[RayCase], camera: CameraModel, repeats: int) -> list[dict[str, Any]]:
    """Return one row per check, the reference first: µs per call and rejections."""
    alpha = CLASSIFIER.test_alpha
    threshold = chi2_quantile(1.0 - alpha, 3) * (EKF.pixel_sigma_px / camera.K[0, 0]) ** 2
    moving = np.array([case.moving for case in cases])
    functions: list[tuple[str, bool, Callable[[RayCase], bool]]] = [
        ('reference: cv2.triangulatePoints + reprojection chi-square', False,
         lambda case: reference_rejects(case, threshold)),
    ]  # fmt: skip
    for label, posed, with_point, accepted in RAY_VARIANTS:

        def ours(case: RayCase, posed: bool = posed, with_point: bool = with_point) -> bool:
            first, middle, last = case.posed if posed else case.views
            point = case.point if with_point else None
            return three_ray_test(first, middle, last, alpha, point=point).result.rejected

        functions.append((label, accepted, ours))
    for label, posed in (('known poses', False), ('pose covariance', True)):

        def score(case: RayCase, posed: bool = posed) -> bool:
            views = case.track_posed if posed else case.track_views
            test = motion_score_test(views, alpha, case.point)
            return test is not None and test.result.rejected

        functions.append((f'motion_score_test over all views, {label}', False, score))
    rows = []
    for label, accepted, function in functions:
        micros, rejected = time_calls(function, cases, repeats)
        rows.append({
            'variant': label,
            'accepted_variant': accepted,
            'median_us': float(np.median(micros)),
            'p95_us': float(np.percentile(micros, 95)),
            'rejected_static': float(np.mean(rejected[~moving])) if np.any(~moving) else None,
            'rejected_moving': float(np.mean(rejected[moving])) if np.any(moving) else None,
        })  # fmt: skip
        print(f'{label}: median {rows[-1]["median_us"]:.1f} us', flush=True)
    return rows


# --- report ----------------------------------------------------------------------------------

REFERENCE_NOTES = """\
Why these references:

- cv2.KalmanFilter (6 states, 2-D measurement, C++) per feature is what one filter object per
  feature costs when its arithmetic is compiled and a node loops over the features in
  Python: two binding calls per feature and frame. Its model is simpler than ours (linear,
  6 states, no projection, no Joseph form, no renormalization), so it is a floor on
  per-feature filtering cost; ours / cv2 above 1 means batching in numpy beats looping over
  compiled per-feature filters.
- The same EKF one feature per call (the core's functions on N = 1 arrays) does the same
  arithmetic (its final states match the batched run, last column); ours / one per call is
  what batching buys.
- The three-ray check in compiled code (cv2.triangulatePoints from the outer views,
  reprojection into the three views, chi-square(3) on the reprojection error at the pixel
  noise, same level) answers the same question with no pose uncertainty, no covariance
  propagation and isotropic noise: the least a "do three rays meet" test costs from the same
  rays. Ours / reference is the price of the uncertain projective test (Pluecker lines with
  their covariances, pose covariance, rank-3 pseudo-inverse, motion visibility).
"""


def render_report(result: dict[str, Any]) -> str:
    """Return the Markdown report of ``result`` (the JSON content)."""
    meta, acceptance = result['meta'], result['acceptance']
    lines = [
        '# Shadow filter: EKF updates/s and three-ray test time on one core',
        '',
        f'{meta["date"]}; {meta["platform"]}, {meta["cpus"]} CPUs, pinned to {meta["pinned"]}, '
        f'Python {meta["python"]}, numpy {meta["numpy"]}, OpenCV {meta["opencv"]}; commit '
        f'{meta["commit"]}. Simulated run seed {meta["seed"]} ({meta["frames"]} frames at 30 Hz); '
        f'best of {meta["repeats"]} passes.',
        '',
        f'EKF predict + update, N features per frame over {meta["ekf_frames"]} frames in '
        'which all of them are tracked (updates/s = N x frames / time):',
        '',
        '| N | ours, batched: updates/s | µs/update | cv2.KalmanFilter per feature: '
        'updates/s | ours / cv2 | same EKF, one feature per call: updates/s '
        '| ours / one per call | max state difference |',
        '|---:|---:|---:|---:|---:|---:|---:|---:|',
    ]
    for row in result['ekf']:
        ours = row['ours_updates_per_s']
        lines.append(
            f'| {row["features"]} | {ours:.0f} | {1e6 / ours:.1f} '
            f'| {row["cv2_kalman_updates_per_s"]:.0f} '
            f'| {ours / row["cv2_kalman_updates_per_s"]:.2f} '
            f'| {row["per_feature_updates_per_s"]:.0f} '
            f'| {ours / row["per_feature_updates_per_s"]:.1f} '
            f'| {row["per_feature_max_state_difference"]:.1e} |'
        )
    kalman = result['ekf'][-1]['cv2_kalman_updates_per_s']
    lines += [
        '',
        '`ShadowFilter.process` over the whole run (every observed feature predicted and '
        'updated, new tracks, classification, handovers, reports):',
        '',
        '| poses | features/frame | features/s | / cv2 per feature (N = 150) '
        '| ms/frame median | p95 | max | three-ray tests (time) | score tests (time) '
        '| decided static / dynamic |',
        '|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|',
    ]
    for row in result['process']:
        lines.append(
            f'| {row["poses"]} | {row["features"] / row["frames"]:.0f} '
            f'| {row["features_per_s"]:.0f} | {row["features_per_s"] / kalman:.2f} '
            f'| {row["ms_per_frame_median"]:.2f} | {row["ms_per_frame_p95"]:.2f} '
            f'| {row["ms_per_frame_max"]:.2f} '
            f'| {row["three_ray_tests"]} ({100 * row["share_in_three_ray_tests"]:.0f} %) '
            f'| {row["score_tests"]} ({100 * row["share_in_score_tests"]:.0f} %) '
            f'| {row["static_decisions"]} / {row["dynamic_decisions"]} |'
        )
    reference = result['three_ray'][0]['median_us']
    lines += [
        '',
        f'Three-ray test per call on {meta["ray_cases_static"]} static and '
        f'{meta["ray_cases_moving"]} moving triples (one warm-up pass, then {meta["repeats"]} '
        f'passes pooled), level {CLASSIFIER.test_alpha:.5f} as the filter runs it; the score '
        f'test gets all views from the first to the last (median {meta["ray_case_views"]}):',
        '',
        '| check | median µs | p95 µs | / reference (median) | static rejected '
        '| moving rejected |',
        '|---|---:|---:|---:|---:|---:|',
    ]
    for row in result['three_ray']:
        lines.append(
            f'| {row["variant"]} | {row["median_us"]:.1f} | {row["p95_us"]:.1f} '
            f'| {row["median_us"] / reference:.1f} | {_percent(row["rejected_static"])} '
            f'| {_percent(row["rejected_moving"])} |'
        )
    lines += [
        '',
        REFERENCE_NOTES,
        f'Acceptance: at least {ACCEPT_UPDATES_PER_S:.0f} feature updates/s (slowest of the EKF '
        f'rows and process): {acceptance["slowest_updates_per_s"]:.0f} -> '
        f'**{_verdict(acceptance["updates_passed"])}**; one three-ray test in at most '
        f"{ACCEPT_TEST_MS} ms (median of the filter's own call, slower pose variant): "
        f'{acceptance["test_ms"]:.3f} ms (p95 {acceptance["test_p95_ms"]:.3f} ms) -> '
        f'**{_verdict(acceptance["test_passed"])}**.',
        '',
    ]
    return '\n'.join(lines)


def _percent(value: float | None) -> str:
    return '—' if value is None else f'{100 * value:.1f} %'


def _verdict(passed: bool) -> str:
    return 'PASS' if passed else 'FAIL'


def acceptance_of(result: dict[str, Any]) -> dict[str, Any]:
    """Return the two acceptance checks of the issue."""
    rates = [row['ours_updates_per_s'] for row in result['ekf']]
    rates += [row['features_per_s'] for row in result['process']]
    filter_calls = [row for row in result['three_ray'] if row['accepted_variant']]
    slowest = max(filter_calls, key=lambda row: row['median_us'])
    return {
        'slowest_updates_per_s': min(rates),
        'updates_passed': min(rates) >= ACCEPT_UPDATES_PER_S,
        'test_ms': slowest['median_us'] * 1e-3,
        'test_p95_ms': slowest['p95_us'] * 1e-3,
        'test_passed': slowest['median_us'] * 1e-3 <= ACCEPT_TEST_MS,
    }


def build_arg_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seed', type=int, default=0, help='seed of the simulated run')
    parser.add_argument('--repeats', type=int, default=5, help='timed passes')
    parser.add_argument('--ekf-frames', type=int, default=120, help='frames of the EKF window')
    parser.add_argument('--ray-tests', type=int, default=500, help='three-ray triples timed')
    parser.add_argument('--cpu', type=int, default=None, help='CPU to pin to (default: last)')
    parser.add_argument(
        '--output', type=Path, default=DEFAULT_OUTPUT, help='Markdown report (JSON next to it)'
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_arg_parser().parse_args(argv)
    pinned = pin_to_one_core(args.cpu)
    run = simulate_dynamic_scene(args.seed)
    camera = camera_of(run)
    ekf = measure_ekf(run, camera, args.ekf_frames, args.repeats, args.seed)
    process = measure_process(run, camera, args.repeats)
    cases = ray_cases(run, camera, args.ray_tests, args.seed)  # after process: a leaner heap
    result: dict[str, Any] = {
        'meta': {
            **run_meta(pinned),
            'seed': args.seed,
            'repeats': args.repeats,
            'frames': len(run.frames),
            'ekf_frames': args.ekf_frames,
            'ray_cases_static': sum(not case.moving for case in cases),
            'ray_cases_moving': sum(case.moving for case in cases),
            'ray_case_views': int(np.median([len(case.track_views) for case in cases])),
        },
        'ekf': ekf,
        'process': process,
        'three_ray': measure_rays(cases, camera, args.repeats),
    }
    result['acceptance'] = acceptance_of(result)
    report = render_report(result)
    write_atomically(args.output.with_suffix('.json'), json.dumps(result, indent=2) + '\n')
    write_atomically(args.output, report)
    print(report)
    accepted = result['acceptance']
    return 0 if accepted['updates_passed'] and accepted['test_passed'] else 1


if __name__ == '__main__':
    sys.exit(main())
