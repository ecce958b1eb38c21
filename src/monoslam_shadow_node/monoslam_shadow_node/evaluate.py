"""shadow_evaluate: the Shadow filter on simulated runs, scored like paper 001's Figs. 2-4.

    shadow_evaluate [--seeds 0-9] [--out out/shadow_eval] [--alpha 0.05] [--quick]

Every run comes from ``slam_sim.core.dynamic_scene`` (true camera poses, 1 px pixel noise)
and is fed frame by frame to ``ShadowFilter``. Two run sets:

- Classification (Fig. 4): the default scene (static points, objects with constant-velocity,
  turning and stop-and-go motion) at ``--alpha`` and at every ``--alphas`` value. A track's
  truth is its point's ``point_moving`` flag (a stop-and-go object is "moving" even while it
  stands still); its status is that of its last Decision, PENDING if it never got one.
  Frames to decide is Decision.frames_since_first.
- Consistency (Figs. 2-3): scenes whose objects follow the filter's own process model
  (``motions=('model',)``, one point per object), at ``--alpha``. Static features are
  scored in these runs and, separately, in the classification runs at ``--alpha``.

Writes ``shadow_eval.json`` (configuration, totals, per seed, alpha sweep, failures) and the
PNG figures of ``evaluation_report`` into ``--out``; prints a summary; logs progress with
rate and ETA on stderr.

Parallax allows (window W = ``--window-frames``): the track was observed W frames after its
first sight (tracks are contiguous in the simulation), and the angle at the point between
the directions to the camera centres of first sight and of W frames later reached the
classifier's ``min_parallax_rad``. Everything is true: the point's position at first sight
and the true centres. For a moving point the position at first sight is held fixed, so the
angle is the parallax the camera's own motion offers; the object's motion is left out
because the static-hypothesis triangulation cannot use it (it turns into a wrong depth), and
counting it would call a fast, far, barely-triangulable object "allowed". The camera's
baseline rule (``min_baseline_m``) is not part of the criterion; it is reported beside it.

Consistency runs (the paper's Fig. 3 experiment): the simulation's ``model`` objects, which
move exactly as the filter's process model says, and the filter as a tracker alone
(``classify`` off), so every feature stays in its EKF for as long as it is tracked. With the
classifier on, handing features over would choose which estimates remain: the static
features still pending late are the ones the tests could not decide or wrongly rejected, a
sample biased towards large errors (it is still reported, as ``static_classification_runs``).
A model object is born at a random frame of the run's first half with v ~ N(0, sigma^2 I3),
the filter's prior; a track first seen at its point's birth starts from exactly that prior
(``moving_first_seen_at_birth``, the consistency test proper). A model object can also leave
view and come back, and a later track of it starts from the prior while the truth has walked
on (velocity variance sigma^2 + q t): ``moving`` holds all tracks. Static points have zero
velocity, a value at the prior's mean, so their NEES is expected below 3 (conservative).

Samples: one per TrackReport with ``defined`` true (inverse depth more than 3 sigma above
zero: skipped before that, since the reported position then sits at 1000 m along the ray)
and status PENDING or DYNAMIC. A STATIC report (the handover frame) carries the handover
triangulation, not the EKF; handovers are scored separately from the classification runs,
with the Handover's own position and covariance. Error e = position - true position in that
frame (map, m); NEES e' P^-1 e (3 dof). The average NEES at age a (frames since first sight)
is the mean over the n samples of that age, with the 95 % band chi2(3n) quantiles / n. Note
that the ``defined`` selection depends on the estimate itself, and samples of one track at
successive ages are correlated.

A run the filter raises on is left out of every statistic, listed under ``failures`` in the
report and in the summary (with its traceback on stderr), and makes the exit status 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
import traceback
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2
from scipy.stats import t as t_dist

from monoslam_shadow_node.core.rays import ray_angle
from monoslam_shadow_node.core.shadow_filter import (
    DYNAMIC,
    PENDING,
    STATIC,
    STATUS_NAMES,
    ClassifierConfig,
    Decision,
    FrameInput,
    Handover,
    ShadowConfig,
    ShadowFilter,
)
from monoslam_shadow_node.evaluation_report import summary_text, write_figures
from slam_core.camera import CameraModel
from slam_core.cli import console_main
from slam_core.files import write_json
from slam_core.progress import ProgressReporter
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import DynamicSceneRun, simulate_dynamic_scene

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]
NEES_DOF = 3
BAND_PROBABILITY = 0.95
ONE_AXIS_3SIGMA = 0.9973002039367398  # P(|N(0, 1)| <= 3)
QUICK_DURATION_S = 4.0


# --- running the filter ---------------------------------------------------------------------


class FilterRunError(RuntimeError):
    """The Shadow filter raised on a simulated run (the message names seed and frame)."""


@dataclass(frozen=True, eq=False)
class FilterRecord:
    """What the filter said on one run. Track reports as flat arrays over samples S: track id,
    frame, status, defined, position (S, 3) m and covariance (S, 3, 3) m^2 in map; decisions
    by track id as (frame, Decision) (the last one if a track got several: ``redecided``
    counts those); handovers as (frame, Handover); filter wall time (s)."""

    track_id: IntArray
    frame: IntArray
    status: IntArray
    defined: BoolArray
    position: FloatArray
    covariance: FloatArray
    decisions: dict[int, tuple[int, Decision]]
    handovers: list[tuple[int, Handover]]
    redecided: int
    runtime_s: float


def camera_model(run: DynamicSceneRun) -> CameraModel:
    """Return the filter's camera model of the run's CameraInfo."""
    info = run.camera.camera_info()
    return CameraModel.from_camera_info(
        info.width, info.height, info.k, info.d, info.distortion_model
    )


def run_filter(run: DynamicSceneRun, config: ShadowConfig) -> FilterRecord:
    """Feed every frame (true pose, noisy pixels) to a new ShadowFilter; return its record.
    Raises FilterRunError if the filter raises."""
    shadow = ShadowFilter(camera_model(run), config)
    ids: list[int] = []
    frames: list[int] = []
    statuses: list[int] = []
    defined: list[bool] = []
    positions: list[FloatArray] = []
    covariances: list[FloatArray] = []
    decisions: dict[int, tuple[int, Decision]] = {}
    handovers: list[tuple[int, Handover]] = []
    redecided, runtime_s = 0, 0.0
    for index, frame in enumerate(run.frames):
        started = time.perf_counter()
        try:
            result = shadow.process(
                FrameInput(
                    frame.stamp_ns,
                    frame.camera_rotation,
                    frame.camera_position,
                    frame.track_ids,
                    frame.pixels,
                )
            )
        except Exception as error:
            raise FilterRunError(
                f'seed {run.seed}, frame {index}: {type(error).__name__}: {error}'
            ) from error
        runtime_s += time.perf_counter() - started
        for decision in result.decisions:
            redecided += decision.id in decisions
            decisions[decision.id] = (index, decision)
        handovers += [(index, handover) for handover in result.handovers]
        for track in result.tracks:
            ids.append(track.id)
            frames.append(index)
            statuses.append(track.status)
            defined.append(bool(track.defined))
            positions.append(track.position)
            covariances.append(track.position_covariance)
    return FilterRecord(
        np.array(ids, dtype=np.int64),
        np.array(frames, dtype=np.int64),
        np.array(statuses, dtype=np.int64),
        np.array(defined, dtype=bool),
        np.array(positions, dtype=np.float64).reshape(-1, 3),
        np.array(covariances, dtype=np.float64).reshape(-1, 3, 3),
        decisions,
        handovers,
        redecided,
        runtime_s,
    )


# --- truth ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrackTruth:
    """A track's point, whether it moves, its motion kind ('static' for static points) and
    the frames of its first and last sighting."""

    point: int
    moving: bool
    motion: str
    first_frame: int
    last_frame: int


def track_truths(run: DynamicSceneRun) -> dict[int, TrackTruth]:
    """Return the truth of every track id in the run."""
    spans: dict[int, list[int]] = {}
    for index, frame in enumerate(run.frames):
        for track_id in frame.track_ids.tolist():
            spans.setdefault(track_id, [index, index])[1] = index
    truths = {}
    for track_id, (first, last) in spans.items():
        point = run.track_point[track_id]
        owner = int(run.point_object[point])
        motion = run.object_motion[owner] if owner >= 0 else 'static'
        truths[track_id] = TrackTruth(point, bool(run.point_moving[point]), motion, first, last)
    return truths


def view_parallax_rad(point: FloatArray, centre_a: FloatArray, centre_b: FloatArray) -> float:
    """Return the angle (rad) at ``point`` (3,) between the directions to two centres (3,)."""
    a, b = centre_a - point, centre_b - point
    norm_a, norm_b = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    if norm_a == 0.0 or norm_b == 0.0:
        return math.nan
    return ray_angle(a / norm_a, b / norm_b)


# --- classification -------------------------------------------------------------------------


@dataclass(frozen=True)
class Outcome:
    """One track's classification: truth, final status, frames from first sight to decision
    (-1: undecided), parallax (rad) and baseline (m) of the deciding test (NaN: undecided),
    the true window parallax (rad, NaN if the track ended earlier), its baseline (m) and
    whether parallax allows a decision within the window."""

    track_id: int
    moving: bool
    motion: str
    status: int
    frames_to_decide: int
    decision_parallax_rad: float
    decision_baseline_m: float
    window_parallax_rad: float
    window_baseline_m: float
    parallax_allows: bool


def track_outcomes(
    run: DynamicSceneRun, record: FilterRecord, *, window_frames: int, min_parallax_rad: float
) -> list[Outcome]:
    """Return every track's Outcome (module docstring: 'parallax allows')."""
    centres = np.array([frame.camera_position for frame in run.frames])
    outcomes = []
    for track_id, truth in sorted(track_truths(run).items()):
        parallax, baseline = math.nan, math.nan
        later = truth.first_frame + window_frames
        if truth.last_frame >= later:
            point = run.point_positions[truth.first_frame, truth.point]
            first_centre, later_centre = centres[truth.first_frame], centres[later]
            parallax = view_parallax_rad(point, first_centre, later_centre)
            baseline = float(np.linalg.norm(later_centre - first_centre))
        status, frames, decision_parallax, decision_baseline = PENDING, -1, math.nan, math.nan
        if track_id in record.decisions:
            _, decision = record.decisions[track_id]
            status, frames = decision.status, decision.frames_since_first
            decision_parallax, decision_baseline = decision.parallax_rad, decision.baseline_m
        allows = bool(parallax >= min_parallax_rad)  # False for NaN
        outcomes.append(
            Outcome(
                track_id,
                truth.moving,
                truth.motion,
                status,
                frames,
                decision_parallax,
                decision_baseline,
                parallax,
                baseline,
                allows,
            )
        )
    return outcomes


def status_name(status: int) -> str:
    """Return the name of a status code (its number for codes the core does not name)."""
    return STATUS_NAMES.get(status, str(status))


def confusion_counts(
    outcomes: Iterable[Outcome], *, by_motion: bool = False
) -> dict[str, dict[str, int]]:
    """Return counts {truth: {status name: n}}, truth 'static'/'moving' (or the motion kind
    when ``by_motion``); every row has STATIC, DYNAMIC and PENDING, zeros included."""
    table: dict[str, dict[str, int]] = {}
    if not by_motion:
        table = {'static': {}, 'moving': {}}
    for outcome in outcomes:
        truth = outcome.motion if by_motion else ('moving' if outcome.moving else 'static')
        row = table.setdefault(truth, {})
        name = status_name(outcome.status)
        row[name] = row.get(name, 0) + 1
    for row in table.values():
        for status in (STATIC, DYNAMIC, PENDING):
            row.setdefault(status_name(status), 0)
    return table


def _ratio(numerator: int, denominator: int) -> float:
    return numerator / denominator if denominator else math.nan


def classification_rates(table: Mapping[str, Mapping[str, int]]) -> dict[str, float | int]:
    """Return the error rates of a static/moving confusion table."""
    static, moving = table.get('static', {}), table.get('moving', {})
    names = (status_name(STATIC), status_name(DYNAMIC))
    static_decided = sum(static.get(name, 0) for name in names)
    moving_decided = sum(moving.get(name, 0) for name in names)
    static_called_dynamic = static.get(status_name(DYNAMIC), 0)
    moving_called_static = moving.get(status_name(STATIC), 0)
    return {
        'static_called_dynamic': static_called_dynamic,
        'static_called_dynamic_of_decided': _ratio(static_called_dynamic, static_decided),
        'static_called_dynamic_of_all': _ratio(static_called_dynamic, sum(static.values())),
        'moving_called_static': moving_called_static,
        'moving_called_static_of_decided': _ratio(moving_called_static, moving_decided),
        'moving_called_dynamic_of_all': _ratio(
            moving.get(status_name(DYNAMIC), 0), sum(moving.values())
        ),
        'static_decided_of_all': _ratio(static_decided, sum(static.values())),
        'moving_decided_of_all': _ratio(moving_decided, sum(moving.values())),
    }


def latency_summary(outcomes: Sequence[Outcome], *, window_frames: int) -> dict[str, Any]:
    """Return frames from first sight to decision over the decided outcomes (median, p90) and
    the fraction decided within ``window_frames``, of the decided and of all outcomes."""
    frames = np.array([o.frames_to_decide for o in outcomes if o.frames_to_decide >= 0])
    within = int(np.count_nonzero(frames <= window_frames))
    return {
        'features': len(outcomes),
        'decided': len(frames),
        'median_frames': float(np.median(frames)) if len(frames) else math.nan,
        'p90_frames': float(np.percentile(frames, 90)) if len(frames) else math.nan,
        'within_window_of_decided': _ratio(within, len(frames)),
        'within_window_of_all': _ratio(within, len(outcomes)),
    }


def classification_summary(
    outcomes: Sequence[Outcome], *, window_frames: int, min_baseline_m: float
) -> dict[str, Any]:
    """Return confusion tables, rates and decision latencies of a set of outcomes, and how
    many tracks parallax allows although their window baseline is below ``min_baseline_m``."""
    allowed = [o for o in outcomes if o.parallax_allows]
    table = confusion_counts(outcomes)
    latency = {}
    for group, keep in (
        ('all', lambda o: True),
        ('static', lambda o: not o.moving),
        ('moving', lambda o: o.moving),
    ):
        latency[group] = {
            'all_features': latency_summary(
                [o for o in outcomes if keep(o)], window_frames=window_frames
            ),
            'parallax_allows': latency_summary(
                [o for o in allowed if keep(o)], window_frames=window_frames
            ),
        }
    short_baseline = [o for o in allowed if o.window_baseline_m < min_baseline_m]
    return {
        'tracks': len(outcomes),
        'confusion': table,
        'confusion_by_motion': confusion_counts(outcomes, by_motion=True),
        'confusion_parallax_allows': confusion_counts(allowed),
        'rates': classification_rates(table),
        'latency': latency,
        'parallax_allows_with_baseline_below_min': len(short_baseline),
    }


def moving_called_static_details(
    run: DynamicSceneRun, record: FilterRecord, outcomes: Sequence[Outcome]
) -> list[dict[str, Any]]:
    """Return, for every moving track decided STATIC, how it moved between first sight and
    the decision: true displacement (m), mean and largest speed (m/s)."""
    truths = track_truths(run)
    details = []
    for outcome in outcomes:
        if not (outcome.moving and outcome.status == STATIC):
            continue
        truth = truths[outcome.track_id]
        decided_frame = record.decisions[outcome.track_id][0]
        path = run.point_positions[truth.first_frame : decided_frame + 1, truth.point]
        speeds = np.linalg.norm(
            run.point_velocities[truth.first_frame : decided_frame + 1, truth.point], axis=1
        )
        details.append(
            {
                'seed': run.seed,
                'track_id': outcome.track_id,
                'motion': outcome.motion,
                'first_frame': truth.first_frame,
                'decided_frame': decided_frame,
                'frames_to_decide': outcome.frames_to_decide,
                'decision_parallax_deg': math.degrees(outcome.decision_parallax_rad),
                'decision_baseline_m': outcome.decision_baseline_m,
                'true_displacement_m': float(np.linalg.norm(path[-1] - path[0])),
                'true_mean_speed_m_s': float(speeds.mean()),
                'true_max_speed_m_s': float(speeds.max()),
            }
        )
    return details


def status_at(decided: Mapping[int, tuple[int, int]], track_id: int, frame: int) -> int:
    """Return a track's status as of ``frame``; ``decided`` maps track id to (decision frame,
    status)."""
    decided_frame, status = decided.get(track_id, (-1, PENDING))
    return status if 0 <= decided_frame <= frame else PENDING


def status_timeline(
    track_ids_per_frame: Sequence[IntArray], decided: Mapping[int, tuple[int, int]]
) -> IntArray:
    """Return counts (K, 3) of the features visible in each frame that are PENDING, STATIC,
    DYNAMIC as of that frame (other status codes count as PENDING)."""
    counts = np.zeros((len(track_ids_per_frame), 3), dtype=np.int64)
    column = {PENDING: 0, STATIC: 1, DYNAMIC: 2}
    for index, ids in enumerate(track_ids_per_frame):
        for track_id in ids.tolist():
            counts[index, column.get(status_at(decided, track_id, index), 0)] += 1
    return counts


# --- consistency ----------------------------------------------------------------------------


def nees(errors: FloatArray, covariances: FloatArray) -> FloatArray:
    """Return e' P^-1 e (N,) of errors (N, d) and covariances (N, d, d), by solving; NaN
    where P is singular or not finite."""
    values = np.full(len(errors), np.nan)
    finite = np.all(np.isfinite(errors), axis=1) & np.all(np.isfinite(covariances), axis=(1, 2))
    for index in np.flatnonzero(finite):
        try:
            solved = np.linalg.solve(covariances[index], errors[index])
        except np.linalg.LinAlgError:
            continue
        values[index] = float(errors[index] @ solved)
    return values


def within_sigma(errors: FloatArray, covariances: FloatArray, sigmas: float = 3.0) -> BoolArray:
    """Return (N, d): whether each error component lies within ``sigmas`` standard
    deviations (sqrt of the covariance diagonal)."""
    deviation = np.sqrt(np.maximum(np.diagonal(covariances, axis1=1, axis2=2), 0.0))
    return np.asarray(np.abs(errors) <= sigmas * deviation)


def average_nees_band(
    counts: IntArray, *, dof: int = NEES_DOF, probability: float = BAND_PROBABILITY
) -> tuple[FloatArray, FloatArray]:
    """Return the two-sided ``probability`` band (low, high) (A,) of the mean of n (A,)
    independent chi2(dof) samples: chi2(dof n) quantiles / n; NaN where n = 0."""
    n = np.asarray(counts, dtype=np.float64)
    safe = np.maximum(n, 1.0)
    tail = 0.5 * (1.0 - probability)
    low = chi2.ppf(tail, dof * safe) / safe
    high = chi2.ppf(1.0 - tail, dof * safe) / safe
    return np.where(n > 0, low, np.nan), np.where(n > 0, high, np.nan)


def nees_by_age(ages: IntArray, values: FloatArray) -> tuple[IntArray, FloatArray, IntArray]:
    """Return the distinct ages (A,), the mean NEES at each (A,) and the sample counts (A,),
    over finite values only."""
    finite = np.isfinite(values)
    unique, inverse = np.unique(ages[finite], return_inverse=True)
    counts = np.bincount(inverse, minlength=len(unique))
    sums = np.bincount(inverse, weights=values[finite], minlength=len(unique))
    means = sums / np.maximum(counts, 1)
    return unique.astype(np.int64), means, counts.astype(np.int64)


@dataclass(frozen=True, eq=False)
class ErrorSamples:
    """Position errors (S, 3) m with covariances (S, 3, 3), ages (S,) in frames since first
    sight, track ids (S,) and frames (S,), plus how many reports were skipped as undefined."""

    errors: FloatArray
    covariances: FloatArray
    ages: IntArray
    track_ids: IntArray
    frames: IntArray
    skipped_undefined: int = 0
    runs: IntArray | None = None  # (S,) which concatenated part (run) each sample came from

    def track_keys(self) -> IntArray:
        """Return (S,) one key per track: track ids are per run, so the run is part of it."""
        runs = self.runs if self.runs is not None else np.zeros(len(self.ages), np.int64)
        return np.asarray(runs * (1 << 32) + self.track_ids, dtype=np.int64)

    @staticmethod
    def concatenate(parts: Sequence[ErrorSamples]) -> ErrorSamples:
        """Return all parts' samples in one (track ids are per run: not unique across parts)."""
        if not parts:
            return ErrorSamples(
                np.zeros((0, 3)), np.zeros((0, 3, 3)), *(np.zeros(0, np.int64),) * 3
            )
        return ErrorSamples(
            np.concatenate([p.errors for p in parts]),
            np.concatenate([p.covariances for p in parts]),
            np.concatenate([p.ages for p in parts]),
            np.concatenate([p.track_ids for p in parts]),
            np.concatenate([p.frames for p in parts]),
            sum(p.skipped_undefined for p in parts),
            np.concatenate([np.full(len(p.ages), i, np.int64) for i, p in enumerate(parts)]),
        )


def error_samples(
    run: DynamicSceneRun,
    record: FilterRecord,
    *,
    moving: bool,
    at_birth: bool = False,
) -> ErrorSamples:
    """Return the EKF position errors of the run's moving (or static) tracks (module
    docstring: which samples enter); ``at_birth``: only tracks first seen in the frame their
    point came into existence."""
    truths = track_truths(run)
    first = np.array([truths[i].first_frame for i in record.track_id.tolist()], dtype=np.int64)
    points = np.array([truths[i].point for i in record.track_id.tolist()], dtype=np.int64)
    keep = np.asarray(run.point_moving[points] == moving) & (record.status != STATIC)
    if at_birth:
        keep &= first == run.point_birth_frame[points]
    skipped = int(np.count_nonzero(keep & ~record.defined))
    keep &= record.defined
    truth = run.point_positions[record.frame[keep], points[keep]]
    return ErrorSamples(
        record.position[keep] - truth,
        record.covariance[keep],
        record.frame[keep] - first[keep],
        record.track_id[keep],
        record.frame[keep],
        skipped,
    )


def handover_samples(run: DynamicSceneRun, record: FilterRecord, *, moving: bool) -> ErrorSamples:
    """Return the errors of the handovers (triangulated static positions) of moving or
    static tracks against the truth in the handover frame."""
    truths = track_truths(run)
    rows = [(frame, h) for frame, h in record.handovers if truths[h.id].moving == moving]
    if not rows:
        return ErrorSamples.concatenate([])
    points = np.array([truths[h.id].point for _, h in rows])
    frames = np.array([frame for frame, _ in rows], dtype=np.int64)
    first = np.array([truths[h.id].first_frame for _, h in rows], dtype=np.int64)
    return ErrorSamples(
        np.array([h.position for _, h in rows]) - run.point_positions[frames, points],
        np.array([h.position_covariance for _, h in rows]),
        frames - first,
        np.array([h.id for _, h in rows], dtype=np.int64),
        frames,
    )


def track_mean_nees(samples: ErrorSamples, values: FloatArray) -> dict[str, Any]:
    """Return the mean NEES of each track averaged over tracks, with its 95 % t-interval.

    Successive samples of one track are correlated, so the band of the overall mean that
    assumes independent samples is far too narrow; tracks are independent, so a test over
    per-track means is sound: a consistent filter has E[mean] = 3, and ``consistent`` says
    whether 3 lies inside the interval."""
    finite = np.isfinite(values)
    _, inverse = np.unique(samples.track_keys()[finite], return_inverse=True)
    counts = np.bincount(inverse)
    means = np.bincount(inverse, weights=values[finite]) / np.maximum(counts, 1)
    if len(means) < 2:
        return {'tracks': len(means), 'mean': math.nan, 'ci95': [math.nan, math.nan],
                'consistent': None}  # fmt: skip
    centre = float(means.mean())
    half = float(t_dist.ppf(0.975, len(means) - 1) * means.std(ddof=1) / math.sqrt(len(means)))
    return {
        'tracks': len(means),
        'mean': centre,
        'ci95': [centre - half, centre + half],
        'consistent': bool(centre - half <= NEES_DOF <= centre + half),
    }


def consistency_summary(
    samples: ErrorSamples, *, min_samples_per_age: int = 5
) -> tuple[dict[str, Any], dict[str, list[float]]]:
    """Return NEES and 3-sigma statistics of the samples, and the average NEES per age
    (ages with at least ``min_samples_per_age`` samples) with its 95 % band, for plotting."""
    values = nees(samples.errors, samples.covariances)
    finite = np.isfinite(values)
    inside = within_sigma(samples.errors[finite], samples.covariances[finite])
    threshold = float(chi2.ppf(BAND_PROBABILITY, NEES_DOF))
    ages, means, counts = nees_by_age(samples.ages, values)
    kept = counts >= min_samples_per_age
    low, high = average_nees_band(counts[kept])
    in_band = (means[kept] >= low) & (means[kept] <= high)
    overall_low, overall_high = average_nees_band(np.array([int(finite.sum())]))
    per_track = track_mean_nees(samples, values)
    summary = {
        'samples': len(values),
        'tracks': len(np.unique(samples.track_keys())),
        'skipped_undefined': samples.skipped_undefined,
        'singular_or_nonfinite': int(np.count_nonzero(~finite)),
        'nees_mean': float(values[finite].mean()) if finite.any() else math.nan,
        'nees_mean_band_95_if_independent': [float(overall_low[0]), float(overall_high[0])],
        'nees_track_means': per_track,
        'nees_median': float(np.median(values[finite])) if finite.any() else math.nan,
        'nees_median_expected': float(chi2.ppf(0.5, NEES_DOF)),
        'nees_p95': float(np.percentile(values[finite], 95)) if finite.any() else math.nan,
        'fraction_nees_above_chi2_95': _ratio(
            int(np.sum(values[finite] > threshold)), int(finite.sum())
        ),
        'within_3sigma': {
            'x': float(inside[:, 0].mean()) if len(inside) else math.nan,
            'y': float(inside[:, 1].mean()) if len(inside) else math.nan,
            'z': float(inside[:, 2].mean()) if len(inside) else math.nan,
            'pooled': float(inside.mean()) if len(inside) else math.nan,
            'all_axes': float(inside.all(axis=1).mean()) if len(inside) else math.nan,
            'expected_per_axis': ONE_AXIS_3SIGMA,
        },
        'by_age': {
            'min_samples_per_age': min_samples_per_age,
            'ages_evaluated': int(kept.sum()),
            'fraction_of_ages_inside_band_95': _ratio(int(in_band.sum()), int(kept.sum())),
        },
    }
    curve = {
        'age_frames': ages[kept].astype(float).tolist(),
        'mean_nees': means[kept].tolist(),
        'samples': counts[kept].astype(float).tolist(),
        'band_low': low.tolist(),
        'band_high': high.tolist(),
    }
    return summary, curve


# --- the evaluation -------------------------------------------------------------------------


@dataclass(frozen=True)
class Settings:
    """What to evaluate: seeds, the main alpha and the alpha sweep (it includes the main one),
    run length (s), focal length (px), the decision window (frames), model objects per
    consistency run, and the output directory."""

    seeds: tuple[int, ...]
    consistency_seeds: tuple[int, ...]
    alpha: float
    alphas: tuple[float, ...]
    duration_s: float
    focal_px: float
    window_frames: int
    consistency_objects: int
    out: Path
    unchecked_directions: int = ClassifierConfig().unchecked_directions

    def scene(self) -> DynamicSceneConfig:
        """Return the classification runs' scene (the default motions, 1 px noise)."""
        return DynamicSceneConfig(
            duration_s=self.duration_s, focal_px=self.focal_px, pixel_noise_px=1.0
        )

    def model_scene(self) -> DynamicSceneConfig:
        """Return the consistency runs' scene: objects on the filter's own motion model."""
        return dataclasses.replace(
            self.scene(),
            motions=('model',),
            objects=self.consistency_objects,
            points_per_object=1,
            object_radius_m=0.0,
        )

    def shadow(self, alpha: float) -> ShadowConfig:
        """Return the filter's configuration: the defaults with ``alpha`` and the rule's
        ``unchecked_directions``."""
        classifier = ClassifierConfig(alpha=alpha, unchecked_directions=self.unchecked_directions)
        return ShadowConfig(classifier=classifier)


@dataclass
class Collected:
    """Everything the runs produced that the report needs."""

    per_seed: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    outcomes: dict[float, list[Outcome]] = dataclasses.field(default_factory=dict)
    moving_called_static: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    classification_samples: dict[str, list[ErrorSamples]] = dataclasses.field(
        default_factory=dict
    )  # EKF and handover errors of the classification runs, by name
    timeline: dict[str, Any] = dataclasses.field(default_factory=dict)
    consistency_per_seed: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    consistency: dict[str, list[ErrorSamples]] = dataclasses.field(default_factory=dict)
    feature: dict[str, Any] = dataclasses.field(default_factory=dict)
    failures: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    runtime_s: float = 0.0
    frames: int = 0

    def failed(self, kind: str, seed: int, alpha: float, error: FilterRunError) -> None:
        """Note a run the filter raised on (it is left out of every statistic)."""
        self.failures.append({'runs': kind, 'seed': seed, 'alpha': alpha, 'error': str(error)})
        traceback.print_exception(error, file=sys.stderr)


def classify_seed(settings: Settings, seed: int, collected: Collected) -> int:
    """Run one seed at every alpha into ``collected``; return the number of filter runs."""
    run = simulate_dynamic_scene(seed, settings.scene())
    for alpha in settings.alphas:
        config = settings.shadow(alpha)
        try:
            record = run_filter(run, config)
        except FilterRunError as error:
            collected.failed('classification', seed, alpha, error)
            continue
        outcomes = track_outcomes(
            run,
            record,
            window_frames=settings.window_frames,
            min_parallax_rad=config.classifier.min_parallax_rad,
        )
        collected.outcomes.setdefault(alpha, []).extend(outcomes)
        collected.runtime_s += record.runtime_s
        collected.frames += len(run.frames)
        if alpha != settings.alpha:
            continue
        summary = classification_summary(
            outcomes,
            window_frames=settings.window_frames,
            min_baseline_m=config.classifier.min_baseline_m,
        )
        collected.per_seed.append(
            {
                'seed': seed,
                **summary,
                'redecided_tracks': record.redecided,
                'filter_runtime_s': record.runtime_s,
                'ms_per_frame': 1e3 * record.runtime_s / len(run.frames),
            }
        )
        collected.moving_called_static += moving_called_static_details(run, record, outcomes)
        for name, part in (
            ('static_classification_runs', error_samples(run, record, moving=False)),
            ('static_handovers', handover_samples(run, record, moving=False)),
            ('moving_handovers', handover_samples(run, record, moving=True)),
        ):
            collected.classification_samples.setdefault(name, []).append(part)
        if not collected.timeline:
            collected.timeline = timeline_data(run, record)
    return len(settings.alphas)


def timeline_data(run: DynamicSceneRun, record: FilterRecord) -> dict[str, Any]:
    """Return the per-frame status counts and the image-plane snapshot of one run; the
    snapshot frame is the one (after the first third) showing the most moving features."""
    decided = {i: (frame, d.status) for i, (frame, d) in record.decisions.items()}
    ids_per_frame = [frame.track_ids for frame in run.frames]
    moving = [run.point_moving[frame.point_ids] for frame in run.frames]
    start = len(run.frames) // 3
    index = start + int(np.argmax([m.sum() for m in moving[start:]]))
    frame = run.frames[index]
    statuses = [status_at(decided, i, index) for i in frame.track_ids.tolist()]
    return {
        'seed': run.seed,
        'rate_hz': run.config.rate_hz,
        'counts': status_timeline(ids_per_frame, decided),
        'moving_visible': np.array([m.sum() for m in moving]),
        'snapshot_frame': index,
        'pixels': frame.pixels,
        'statuses': np.array(statuses, dtype=np.int64),
        'moving': moving[index],
        'image_size': (run.camera.width, run.camera.height),
    }


def consistency_seed(settings: Settings, seed: int, collected: Collected) -> int:
    """Run one model-motion seed into ``collected``; return the number of filter runs (1)."""
    run = simulate_dynamic_scene(seed, settings.model_scene())
    try:
        record = run_filter(
            run, dataclasses.replace(settings.shadow(settings.alpha), classify=False)
        )
    except FilterRunError as error:
        collected.failed('consistency', seed, settings.alpha, error)
        return 1
    collected.runtime_s += record.runtime_s
    collected.frames += len(run.frames)
    parts = {
        'moving': error_samples(run, record, moving=True),
        'moving_first_seen_at_birth': error_samples(run, record, moving=True, at_birth=True),
        'static': error_samples(run, record, moving=False),
    }
    for name, part in parts.items():
        collected.consistency.setdefault(name, []).append(part)
    moving, _ = consistency_summary(parts['moving'])
    collected.consistency_per_seed.append(
        {'seed': seed, 'moving': moving, 'filter_runtime_s': record.runtime_s}
    )
    ids, counts = np.unique(parts['moving'].track_ids, return_counts=True)
    if len(ids) and counts.max() > collected.feature.get('samples', 0):
        collected.feature = feature_data(run, record, parts['moving'], int(ids[counts.argmax()]))
    return 1


def feature_data(
    run: DynamicSceneRun, record: FilterRecord, samples: ErrorSamples, track_id: int
) -> dict[str, Any]:
    """Return one feature's errors, 3-sigma bounds and paths (Figs. 2 and 3)."""
    mine = samples.track_ids == track_id
    frames = samples.frames[mine]
    point = run.track_point[track_id]
    status = record.decisions[track_id][1].status if track_id in record.decisions else PENDING
    return {
        'seed': run.seed,
        'track_id': track_id,
        'samples': int(mine.sum()),
        'ages': samples.ages[mine],
        'errors': samples.errors[mine],
        'sigmas': np.sqrt(np.diagonal(samples.covariances[mine], axis1=1, axis2=2)),
        'camera_path': np.array([frame.camera_position for frame in run.frames]),
        'true_path': run.point_positions[frames, point],
        'estimates': samples.errors[mine] + run.point_positions[frames, point],
        'status': status_name(status),
    }


def report(settings: Settings, collected: Collected, wall_s: float) -> dict[str, Any]:
    """Return the JSON report: configuration, per seed and total results."""
    shadow = settings.shadow(settings.alpha)
    main_outcomes = collected.outcomes.get(settings.alpha, [])
    sweep = []
    for alpha in settings.alphas:
        table = confusion_counts(collected.outcomes.get(alpha, []))
        sweep.append({'alpha': alpha, 'confusion': table, 'rates': classification_rates(table)})
    consistency = {}
    curves = {}
    for name, parts in (
        *collected.consistency.items(),
        *collected.classification_samples.items(),
    ):
        consistency[name], curves[name] = consistency_summary(ErrorSamples.concatenate(parts))
    feature = collected.feature
    return {
        'config': {
            'seeds': list(settings.seeds),
            'consistency_seeds': list(settings.consistency_seeds),
            'alpha': settings.alpha,
            'alphas': list(settings.alphas),
            'window_frames': settings.window_frames,
            'classification_scene': dataclasses.asdict(settings.scene()),
            'consistency_scene': dataclasses.asdict(settings.model_scene()),
            'shadow': dataclasses.asdict(shadow),
            'poses': 'true camera poses, no pose covariance',
        },
        'classification': {
            'totals': classification_summary(
                main_outcomes,
                window_frames=settings.window_frames,
                min_baseline_m=shadow.classifier.min_baseline_m,
            ),
            'per_seed': collected.per_seed,
            'alpha_sweep': sweep,
            'moving_called_static': collected.moving_called_static,
        },
        'consistency': {
            'totals': consistency,
            'per_seed': collected.consistency_per_seed,
            'average_nees_by_age': curves,
            'representative_feature': {
                key: feature[key] for key in ('seed', 'track_id', 'samples', 'status')
            }
            if feature
            else None,
        },
        'failures': collected.failures,
        'runtime': {
            'wall_s': wall_s,
            'filter_s': collected.runtime_s,
            'frames': collected.frames,
            'filter_ms_per_frame': 1e3 * collected.runtime_s / max(collected.frames, 1),
        },
    }


def figure_inputs(
    settings: Settings, collected: Collected, content: Mapping[str, Any]
) -> dict[str, Any]:
    """Return what ``evaluation_report.write_figures`` draws, as arrays and report parts."""
    outcomes = collected.outcomes.get(settings.alpha, [])
    classifier = settings.shadow(settings.alpha).classifier
    return {
        'confusion': content['classification']['totals']['confusion'],
        'confusion_by_motion': content['classification']['totals']['confusion_by_motion'],
        'alpha_sweep': content['classification']['alpha_sweep'],
        'decisions': {
            'frames_to_decide': np.array([o.frames_to_decide for o in outcomes]),
            'decision_parallax_deg': np.degrees([o.decision_parallax_rad for o in outcomes]),
            'window_parallax_deg': np.degrees([o.window_parallax_rad for o in outcomes]),
            'moving': np.array([o.moving for o in outcomes], dtype=bool),
            'status': np.array([o.status for o in outcomes], dtype=np.int64),
            'window_frames': settings.window_frames,
            'min_parallax_deg': math.degrees(classifier.min_parallax_rad),
        },
        'timeline': collected.timeline,
        'feature': collected.feature,
        'nees_curves': content['consistency']['average_nees_by_age'],
    }


def parse_seeds(text: str) -> tuple[int, ...]:
    """Return seeds from '0-9', '1,4' or '0-3,7'; ValueError if malformed or a range is
    reversed ('5-2' would give no seeds)."""
    seeds: list[int] = []
    for part in text.split(','):
        low, _, high = part.strip().partition('-')
        if not low.isdigit() or (high and not high.isdigit()):
            raise ValueError(f'--seeds {text!r}: use e.g. 0-9, 1,4 or 0-3,7')
        if high and int(high) < int(low):
            raise ValueError(f'--seeds {text!r}: the range {part.strip()} is reversed (low-high)')
        seeds += range(int(low), int(high or low) + 1)
    return tuple(dict.fromkeys(seeds))


def _parse_alphas(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(part) for part in text.split(',') if part.strip())
    except ValueError as error:
        raise argparse.ArgumentTypeError(f'--alphas {text!r}: use e.g. 0.01,0.05,0.1') from error


def _arguments(argv: list[str] | None) -> Settings:
    parser = argparse.ArgumentParser(prog='shadow_evaluate', description=__doc__.splitlines()[0])
    parser.add_argument(
        '--seeds', type=parse_seeds, help='seeds, e.g. 0-9 (default, the acceptance seeds) or 1,4'
    )
    parser.add_argument(
        '--consistency-seeds',
        type=parse_seeds,
        help='seeds of the model-motion runs (default: --seeds)',
    )
    parser.add_argument(
        '--out',
        type=Path,
        default=Path('out/shadow_eval'),
        help='output directory (default out/shadow_eval)',
    )
    parser.add_argument('--duration-s', type=float, help='run length, s (default 20)')
    parser.add_argument(
        '--alpha',
        type=float,
        default=ClassifierConfig().alpha,
        help='classifier significance level (default %(default)s)',
    )
    parser.add_argument(
        '--alphas',
        type=_parse_alphas,
        help='alpha sweep, e.g. 0.01,0.05,0.1 (default; --alpha is added)',
    )
    parser.add_argument(
        '--focal-px',
        type=float,
        default=DynamicSceneConfig().focal_px,
        help='focal length, px (default %(default)s)',
    )
    parser.add_argument(
        '--window-frames',
        type=int,
        default=30,
        help="decision window and 'parallax allows' span (default 30)",
    )
    parser.add_argument(
        '--consistency-objects',
        type=int,
        default=12,
        help='model-motion objects per consistency run (default 12)',
    )
    parser.add_argument(
        '--unchecked-directions',
        type=int,
        default=ClassifierConfig().unchecked_directions,
        help='directions of motion the STATIC rule may leave unchecked: 0 (strict: no moving '
        'feature handed over, slow), 1 (default) or 2',
    )
    parser.add_argument(
        '--quick',
        action='store_true',
        help=f'smoke run: seed 0, {QUICK_DURATION_S:g} s, no alpha sweep',
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    seeds = args.seeds or ((0,) if args.quick else tuple(range(10)))
    if args.alphas is None:
        args.alphas = () if args.quick else (0.01, 0.05, 0.1)
    if args.window_frames < 1 or args.consistency_objects < 1:
        parser.error('--window-frames and --consistency-objects must be at least 1')
    duration = args.duration_s or (
        QUICK_DURATION_S if args.quick else DynamicSceneConfig().duration_s
    )
    try:
        settings = Settings(
            seeds,
            args.consistency_seeds or seeds,
            args.alpha,
            tuple(sorted({args.alpha, *args.alphas})),
            duration,
            args.focal_px,
            args.window_frames,
            args.consistency_objects,
            args.out,
            args.unchecked_directions,
        )
        (
            settings.scene(),
            settings.shadow(args.alpha),
            [settings.shadow(a) for a in settings.alphas],
        )
    except ValueError as error:
        parser.error(str(error))
    return settings


@console_main('shadow_evaluate')
def main(argv: list[str] | None = None) -> int:
    """Run the evaluation; print the summary; write the JSON report and figures to --out.
    Exit status 1 if the filter raised on a run (listed in the report, left out of it)."""
    settings = _arguments(argv)
    started = time.perf_counter()
    total = len(settings.seeds) * len(settings.alphas) + len(settings.consistency_seeds)
    progress = ProgressReporter(total, label='shadow_evaluate', unit=' runs', period_s=0.0)
    collected, done = Collected(), 0
    for seed in settings.seeds:
        done += classify_seed(settings, seed, collected)
        progress.update(done)
    for seed in settings.consistency_seeds:
        done += consistency_seed(settings, seed, collected)
        progress.update(done)
    progress.finish()
    content = report(settings, collected, time.perf_counter() - started)
    figures = write_figures(settings.out, figure_inputs(settings, collected, content))
    content['figures'] = [path.name for path in figures]
    content['runtime']['wall_s'] = time.perf_counter() - started
    write_json(settings.out / 'shadow_eval.json', content)
    print(summary_text(content))  # noqa: T201
    print(f'wrote {settings.out / "shadow_eval.json"} and {len(figures)} figures')  # noqa: T201
    return 1 if collected.failures else 0


if __name__ == '__main__':
    sys.exit(main())
