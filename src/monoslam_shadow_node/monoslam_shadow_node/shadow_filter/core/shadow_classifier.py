"""The Shadow filter's static/dynamic classifier: the rule, when a PENDING feature is tested,
and its score tests (``shadow_decision`` tests and decides).

Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.common.core.feature_status import PENDING
from monoslam_shadow_node.common.core.projective import chi2_quantile
from monoslam_shadow_node.common.core.tracking_noise import TrackingNoise
from monoslam_shadow_node.shadow_filter.core.rays import (
    View,
)
from monoslam_shadow_node.shadow_filter.core.shadow_track import Track
from monoslam_shadow_node.shadow_filter.core.static_fit import (
    MOTION_DOF,
    ROW_CENTRE,
    ROW_DIRECTION,
    ROW_PRECISION,
    ROW_TAU,
    ROW_VISIBILITY,
    MotionScoreTest,
    linked,
    motion_score_test,
    motion_score_tests,
)
from slam_core.arrays import FloatArray
from slam_core.lazy_stats import ncx2
from slam_core.params import (
    AT_LEAST_ONE,
    NON_NEGATIVE,
    POSITIVE,
    PROBABILITY,
    Range,
    check_fields,
    ruled,
)

STATIC_TESTS = ('both', 'three_ray', 'all_view')
"""The choices of ``ClassifierConfig.static_test``."""
TEST_DELAY_FRAMES = 1
"""A test triggered in frame k takes its last ray from frame k + this (white tracking noise)."""
DECORRELATED = math.log(2.0)
"""Offset correlation times between the trigger and a test's last ray (persistent offsets)."""


@dataclass(frozen=True)
class ClassifierConfig:
    """The static/dynamic rule (units in the names); raises ValueError for a bad value."""

    alpha: float = ruled(0.05, range=PROBABILITY)
    min_parallax_rad: float = ruled(
        math.radians(2.0), range=Range(0.0, math.pi, low_open=True, high_open=True)
    )
    parallax_growth: float = ruled(1.5, range=Range(1.0))
    max_tests: int = ruled(6, range=AT_LEAST_ONE)
    min_baseline_m: float = ruled(0.05, range=POSITIVE)
    middle_min_fraction: float = ruled(0.25, range=Range(0.0, 0.5, low_open=True))
    min_detectable_speed_m_s: float = ruled(0.3, range=NON_NEGATIVE)
    detection_power: float = ruled(0.99, range=PROBABILITY)
    unchecked_directions: int = ruled(1, choices=(0, 1, 2))
    static_test: str = ruled('both', choices=STATIC_TESTS)

    def __post_init__(self) -> None:
        check_fields(self)

    @property
    def test_alpha(self) -> float:
        """The level of each test (alpha split over the tests of every round, Bonferroni)."""
        return self.alpha / ((2 if self.static_test == 'both' else 1) * self.max_tests)

    def parallax_for_test(self, index: int) -> float:
        """Return the parallax (rad) test ``index`` (0-based) waits for."""
        return float(self.min_parallax_rad * self.parallax_growth**index)

    @property
    def required_noncentrality(self) -> float:
        """The noncentrality at which the score test rejects with ``detection_power``."""
        return _required_noncentrality(self.test_alpha, self.detection_power)


@lru_cache(maxsize=32)
def _required_noncentrality(alpha: float, power: float) -> float:
    threshold = chi2_quantile(1.0 - alpha, MOTION_DOF)

    def shortfall(noncentrality: float) -> float:
        return float(ncx2.sf(threshold, MOTION_DOF, noncentrality)) - power

    from scipy.optimize import brentq  # here: scipy.optimize costs 0.3 s to import

    return float(brentq(shortfall, 1e-6, 1e4))


@dataclass(frozen=True, eq=False)
class Decision:
    """A classification made in a frame (for evaluation), with its deciding test's geometry."""

    id: int
    status: int
    frames_since_first: int
    parallax_rad: float
    baseline_m: float
    statistic: float


def predicted_visibility(
    tracks: list[Track],
    positions: FloatArray,
    defined: NDArray[np.bool_],
) -> FloatArray:
    """Return per track the predicted noncentrality per (m/s)^2 along each principal direction
    of motion, ascending (N, 3) (0 where not computed), at ``positions`` (N, 3) m."""
    result = np.zeros((len(tracks), 3))
    rows = [
        row
        for row, track in enumerate(tracks)
        if track.status == PENDING
        and track.missed == 0
        and defined[row]
        and track.scheduled_frame < 0
        and len(track.views) >= 3
    ]
    if not rows:
        return result
    # all views of those tracks in one array, summed per track
    counts = np.array([len(tracks[row].views) for row in rows], dtype=np.intp)
    first = np.zeros(len(rows), dtype=np.intp)
    first[1:] = np.cumsum(counts)[:-1]
    segment = np.repeat(np.arange(len(rows)), counts)
    views = np.concatenate([tracks[row].rows[:, ROW_VISIBILITY] for row in rows])
    offset = positions[rows][segment] - views[:, ROW_CENTRE]
    depth = np.einsum('ni,ni->n', views[:, ROW_DIRECTION], offset)
    ahead = ~np.logical_or.reduceat(depth <= 0.0, first)
    weighted = views[:, ROW_PRECISION].reshape(-1, 3, 3) / (depth**2)[:, None, None]
    taus = views[:, ROW_TAU]
    tau = taus - (np.add.reduceat(taus, first) / counts)[segment]
    a0 = np.add.reduceat(weighted, first)
    a1 = np.add.reduceat(tau[:, None, None] * weighted, first)
    a2 = np.add.reduceat((tau * tau)[:, None, None] * weighted, first)
    usable = np.flatnonzero(ahead)
    try:
        eliminated = np.linalg.solve(a0[usable], a1[usable])
    except np.linalg.LinAlgError:  # one is singular: leave it out (0), solve the others alone
        solvable = []
        for index in usable:
            try:
                np.linalg.solve(a0[index], a1[index])
            except np.linalg.LinAlgError:
                continue
            solvable.append(index)
        usable = np.array(solvable, dtype=np.intp)
        eliminated = np.linalg.solve(a0[usable], a1[usable])
    schur = a2[usable] - a1[usable] @ eliminated
    values = np.linalg.eigvalsh(0.5 * (schur + np.swapaxes(schur, 1, 2)))
    result[np.array(rows, dtype=np.intp)[usable]] = np.maximum(values, 0.0)
    return result


@dataclass(frozen=True, eq=False)
class DueTest:
    """A track whose tests run in this frame, with its static position (3,) m and middle view."""

    track: Track
    position: FloatArray
    settings: ClassifierConfig
    parallax: float
    baseline: float
    middle: View


def due_test(
    track: Track,
    position: FloatArray,
    visibility: float,
    frame: int,
    settings: ClassifierConfig,
    noise: TrackingNoise | None = None,
) -> DueTest | None:
    """Schedule the track's next test; return it when due in this frame, else None."""
    if track.tests_run >= settings.max_tests:
        return None
    first_centre, last_centre = track.first_centre, track.last_centre
    baseline = math.dist(last_centre, first_centre)
    speed = settings.min_detectable_speed_m_s
    point = position.tolist()
    if track.scheduled_frame < 0:
        if baseline < settings.min_baseline_m:
            return None
        parallax = _parallax(point, first_centre, last_centre)
        visible = visibility * speed**2
        track.milestone_due = parallax >= settings.parallax_for_test(track.tests_run)
        if track.milestone_due or (
            speed > 0
            and parallax >= settings.min_parallax_rad
            and visible >= settings.required_noncentrality
            and visible >= track.visibility_wait
        ):
            track.scheduled_frame = frame + trigger_delay_frames(track, noise)
            track.predicted_visible = visible
        return None
    if frame < track.scheduled_frame:
        return None
    track.scheduled_frame = -1
    parallax = _parallax(point, first_centre, last_centre)
    middle = _middle_view(track.views, track.centres, settings.middle_min_fraction * baseline)
    if middle is None:
        return None
    return DueTest(track, position, settings, parallax, baseline, middle)


def score_tests(
    dues: list[DueTest], noise: TrackingNoise | None = None
) -> list[MotionScoreTest | None]:
    """Return the score tests (``static_fit``) of due tests (None: no static point)."""
    white = noise is None or noise.white
    alone = [k for k, due in enumerate(dues) if not white or linked(due.track.views)]
    together = sorted(set(range(len(dues))) - set(alone))
    results: list[MotionScoreTest | None] = [None] * len(dues)
    stacked = motion_score_tests(
        [dues[k].track.rows for k in together],
        [dues[k].settings.test_alpha for k in together],
        [dues[k].position for k in together],
    )
    for k, test in zip(together, stacked, strict=True):
        results[k] = test
    for k in alone:
        due = dues[k]
        results[k] = motion_score_test(
            due.track.views, due.settings.test_alpha, due.position, noise=noise
        )
    return results


def trigger_delay_frames(track: Track, noise: TrackingNoise | None) -> int:
    """Return how many frames after the trigger a test runs."""
    if noise is None or noise.white or len(track.views) < 2:
        return TEST_DELAY_FRAMES
    first, last = track.views[0], track.views[-1]
    frames = last.frame - first.frame
    if frames <= 0 or last.stamp_ns <= first.stamp_ns:
        return TEST_DELAY_FRAMES
    frame_s = (last.stamp_ns - first.stamp_ns) * 1e-9 / frames
    return max(TEST_DELAY_FRAMES, math.ceil(DECORRELATED * noise.offset_time_s / frame_s))


def _middle_view(views: list[View], centres: FloatArray, min_distance_m: float) -> View | None:
    """Return the inner view farthest from both ends' ``centres`` (N, 3), if at least
    ``min_distance_m`` from each; else None."""
    if len(views) < 3:
        return None
    inner = centres[1:-1]
    distance = np.minimum(
        np.linalg.norm(inner - centres[0], axis=1),
        np.linalg.norm(inner - centres[-1], axis=1),
    )
    best = int(np.argmax(distance))
    return views[1 + best] if distance[best] >= min_distance_m else None


def _parallax(point: list[float], first: list[float], last: list[float]) -> float:
    """Return the angle (rad) at ``point`` between the camera centres ``first`` and ``last``."""
    a = [point[0] - first[0], point[1] - first[1], point[2] - first[2]]
    b = [point[0] - last[0], point[1] - last[1], point[2] - last[2]]
    norm_a, norm_b = math.hypot(*a), math.hypot(*b)
    if norm_a > 0:
        a = [a[0] / norm_a, a[1] / norm_a, a[2] / norm_a]
    if norm_b > 0:
        b = [b[0] / norm_b, b[1] / norm_b, b[2] / norm_b]
    cross = math.hypot(
        a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]
    )
    return math.atan2(cross, a[0] * b[0] + a[1] * b[1] + a[2] * b[2])


def _unit(vector: FloatArray) -> FloatArray:
    norm = float(np.linalg.norm(vector))
    return vector / norm if norm > 0 else vector
