"""The Shadow filter's decision on a due test: the static tests behind one seam
(``StaticTest``) and ``decide`` (DYNAMIC, STATIC or wait).

Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, STATIC
from monoslam_shadow_node.common.core.projective import RelationTest
from monoslam_shadow_node.common.core.tracking_noise import TrackingNoise
from monoslam_shadow_node.shadow_filter.core.near_static import WAIT_WARNING, implausibly_near
from monoslam_shadow_node.shadow_filter.core.rays import (
    UncertainLine,
    conditioning,
    three_ray_relations,
    viewing_lines,
)
from monoslam_shadow_node.shadow_filter.core.shadow_classifier import (
    ClassifierConfig,
    Decision,
    DueTest,
    due_test,
    score_tests,
)
from monoslam_shadow_node.shadow_filter.core.shadow_track import Track
from monoslam_shadow_node.shadow_filter.core.static_fit import MotionScoreTest
from slam_core.arrays import FloatArray

UNFIT_TESTS = 3
"""Evidence of motion: DYNAMIC after this many due tests in a row, past a parallax milestone,
whose views fix no static point in front of every camera."""
UNFIT_WARNING = 'its views do not fix a static point yet'  # a due test without a fit (counted)


def classify(
    track: Track,
    position: FloatArray,
    visibility: float,
    frame: int,
    settings: ClassifierConfig,
    warnings: list[str],
    noise: TrackingNoise | None = None,
    depth_prior: tuple[float, float] | None = None,
) -> Decision | None:
    """Schedule, test and decide one track (``position`` (3,) m its static estimate); return
    the decision made in this frame, or None."""
    due = due_test(track, position, visibility, frame, settings, noise)
    if due is None:
        return None
    (motion,) = score_tests([due], noise)
    return decide(due, motion, frame, warnings, noise, depth_prior=depth_prior)


def needs_test(due: DueTest, motion: MotionScoreTest | None) -> bool:
    """Whether ``decide`` tests ``due``'s static hypothesis given its score test."""
    if motion is None:
        return False
    return due.track.milestone_due or _decisive(due.settings, motion)


Verdict = RelationTest | ValueError | None
"""A ``StaticTest``'s outcome: the test, the ValueError of a degenerate geometry, or None."""


class StaticTest(Protocol):
    """The seam of the static/dynamic decision: tests due tests given their score tests."""

    def verdicts(
        self, dues: list[DueTest], motions: list[MotionScoreTest | None],
        noise: TrackingNoise | None,
    ) -> list[Verdict]:  # fmt: skip
        """Return one ``Verdict`` per due test, each at its rule's ``test_alpha``."""
        ...


class ThreeRayTest:
    """The paper's test: the first, a middle and the last ray (``rays.three_ray_test``)."""

    def verdicts(
        self, dues: list[DueTest], motions: list[MotionScoreTest | None],
        noise: TrackingNoise | None,
    ) -> list[Verdict]:  # fmt: skip
        """``StaticTest.verdicts``: all the frame's three-ray tests at once."""
        tested = [k for k, due in enumerate(dues) if needs_test(due, motions[k])]
        out: list[Verdict] = [None] * len(dues)
        for k, outcome in zip(
            tested, three_ray_tests([dues[k] for k in tested], noise), strict=True
        ):
            out[k] = outcome
        return out


class AllViewTest:
    """The score test of a constant velocity over all views (``static_fit``)."""

    def verdicts(
        self, dues: list[DueTest], motions: list[MotionScoreTest | None],
        noise: TrackingNoise | None,
    ) -> list[Verdict]:  # fmt: skip
        """``StaticTest.verdicts``: the score tests' own results."""
        return [
            motion.result if motion is not None and needs_test(due, motion) else None
            for due, motion in zip(dues, motions, strict=True)
        ]


class BothTests:
    """Both tests: either rejecting rejects; the verdict carries the three-ray statistic."""

    def verdicts(
        self, dues: list[DueTest], motions: list[MotionScoreTest | None],
        noise: TrackingNoise | None,
    ) -> list[Verdict]:  # fmt: skip
        """``StaticTest.verdicts``: the three-ray verdict, also rejected by the score test."""
        out = ThreeRayTest().verdicts(dues, motions, noise)
        for k, (verdict, motion) in enumerate(zip(out, motions, strict=True)):
            if isinstance(verdict, RelationTest) and motion is not None:
                rejected = verdict.rejected or motion.result.rejected
                out[k] = RelationTest(verdict.statistic, verdict.dof, verdict.threshold, rejected)
        return out


_TESTS: dict[str, StaticTest] = {
    'both': BothTests(), 'three_ray': ThreeRayTest(), 'all_view': AllViewTest()
}  # fmt: skip


def static_test(name: str) -> StaticTest:
    """Return the ``StaticTest`` that ``ClassifierConfig.static_test`` names."""
    return _TESTS[name]


def _decisive(settings: ClassifierConfig, motion: MotionScoreTest) -> bool:
    """Whether the score test's geometry could have seen motion (``decide``)."""
    speed = settings.min_detectable_speed_m_s
    return speed == 0 or (
        motion.visibility[settings.unchecked_directions] * speed**2
        >= settings.required_noncentrality
    )


def three_ray_tests(
    dues: list[DueTest], noise: TrackingNoise | None = None
) -> list[RelationTest | ValueError]:
    """Return the three-ray tests of due tests at once (a ValueError where degenerate)."""
    triples = [(due.track.views[0], due.middle, due.track.views[-1]) for due in dues]
    conditions = [conditioning(*triple) for triple in triples]
    kept = [k for k, (_, scale) in enumerate(conditions) if math.isfinite(scale)]
    lines: list[list[UncertainLine] | None] = [None] * len(dues)
    if kept:
        stacked = viewing_lines(
            [view for k in kept for view in triples[k]],
            np.repeat(np.array([conditions[k][0] for k in kept]), 3, axis=0),
            np.repeat(np.array([conditions[k][1] for k in kept]), 3),
        )
        for index, k in enumerate(kept):
            lines[k] = stacked[3 * index : 3 * index + 3]
    alphas = [due.settings.test_alpha for due in dues]
    return three_ray_relations(triples, lines, alphas, noise)


def decide(
    due: DueTest,
    motion: MotionScoreTest | None,
    frame: int,
    warnings: list[str],
    noise: TrackingNoise | None = None,
    verdict: Verdict = None,
    depth_prior: tuple[float, float] | None = None,
) -> Decision | None:
    """Decide a due test given its score test (``verdict``: if computed already;
    ``depth_prior``: inverse depth mean and sigma, 1/m); return the decision or None."""
    track, settings = due.track, due.settings
    parallax, baseline = due.parallax, due.baseline
    if motion is None:
        track.unfit += 1
        frames = frame - track.first_frame
        if track.milestone_due and track.unfit >= UNFIT_TESTS:
            # evidence of motion (module docstring): the views keep refusing a static point
            track.status, track.decided_frame = DYNAMIC, frame
            track.clear_views()
            return Decision(track.id, DYNAMIC, frames, parallax, baseline, math.nan)
        warnings.append(f'feature {track.id}: {UNFIT_WARNING}')
        return None
    track.unfit = 0
    # Whether a decision is possible is geometry (S), not the test's outcome: when it
    # is not and no parallax milestone is due, nothing is tested and no alpha is spent.
    decisive = _decisive(settings, motion)
    if not decisive:
        # the prediction was optimistic: ask it for half as much again before retrying
        track.visibility_wait = 1.5 * track.predicted_visible
        if not track.milestone_due:
            return None
    if verdict is None:
        (verdict,) = static_test(settings.static_test).verdicts([due], [motion], noise)
    if isinstance(verdict, ValueError):
        warnings.append(f'feature {track.id}: test skipped, degenerate geometry ({verdict})')
        return None
    assert verdict is not None  # needs_test holds here: decisive, or a milestone is due
    track.statistic = verdict.statistic
    track.tests_run += 1
    frames = frame - track.first_frame
    if verdict.rejected:
        track.status, track.decided_frame = DYNAMIC, frame
        track.clear_views()
        return Decision(track.id, DYNAMIC, frames, parallax, baseline, track.statistic)
    if not decisive:
        return None  # accepted, but motion could have gone unseen: wait for more views
    near = None if depth_prior is None else implausibly_near(
        motion.point, track.views, depth_prior, settings.test_alpha
    )  # fmt: skip
    if near is not None:
        warnings.append(f'feature {track.id}: its static fit lies {near:.2f} m along a ray, '
                        f'{WAIT_WARNING}: waiting for more views')  # fmt: skip
        return None
    track.status, track.decided_frame = STATIC, frame
    track.handover = (motion.point, motion.covariance)
    return Decision(track.id, STATIC, frames, parallax, baseline, track.statistic)
