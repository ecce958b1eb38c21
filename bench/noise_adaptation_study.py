"""Study: MonoSLAM adopting the online tracking-noise estimate (``noise_estimate``) mid-run.

``monoslam_evaluate`` runs as usual (every option passes through), with SLAM's frame step
wrapped: each frame the residuals z - h(x+) of the features SLAM measured feed a
``TrackingNoiseEstimator`` (the ``measured`` column of ``bench/noise_estimate_study.py``);
once a second, when the estimate is confident, SLAM's configuration takes it:

* ``--adapt full``: white sigma max(declared, estimated); the offset, when its variance is at
  least ``OFFSET_RELEVANCE`` of the white's, with its correlation time (features added from
  then on get offset states, ``MonoSlamConfig.offset_states``);
* ``--adapt marginal``: white noise only, at max(declared, the estimate's marginal sigma);
* ``--adapt batch``: as ``full``, but the estimator is fed (rebuilt once a second) the
  residuals of every sighting, in the frames SLAM tracked, of the tracks SLAM has measured,
  each against its point triangulated over all its sightings so far with SLAM's poses
  (``noise_estimate_study``'s ``batch`` column: neither the gate nor the filter's moving
  point estimate biases them);
* ``--adapt batch_prior``: as ``batch``, and until the estimate is confident SLAM takes the
  estimator's prior white sigma (``DEFAULT_PRIOR_WHITE_PX``) if it is larger than the
  declared one.

It is a study: the node's own adoption (``estimate_noise``, ``core/noise_monitor``) is
switched off while it runs its own, and the figures it
reaches are in bench/README.md. Run (after ``bash scripts/bootstrap.sh``, about 4 min per
setting on 2 cores)::

    source scripts/env.sh
    python bench/noise_adaptation_study.py --adapt full --seeds 0-19 --variants a,c \\
        --tracking-offset-px 2 --tracking-jump-probability 0.02 --undeclared --out DIR
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import weakref

import numpy as np
from noise_estimate_study import TrackedFrame, feed_fixed_points

from monoslam_shadow_node.monoslam.core.monoslam_types import (
    TRACKING,
    MonoSlamConfig,
    MonoSlamFrame,
)
from monoslam_shadow_node.monoslam.core.noise_estimate import (
    OFFSET_RELEVANCE,
    TrackingNoiseEstimator,
)
from monoslam_shadow_node.monoslam.processor import MonoSlamProcessor, MonoSlamStep
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_evaluation import monoslam_evaluate

ADAPT_PERIOD_NS = 10**9
MODES = ('full', 'marginal', 'batch', 'batch_prior')
ADOPTION = {'batch': 'full', 'batch_prior': 'prior'}  # the batch modes' adoption rules


def _rows(ids: IntArray, wanted: IntArray) -> IntArray:
    """Return the rows of ``ids`` (N,) holding ``wanted`` (M,), each of which is in ids."""
    order = np.argsort(ids)
    return np.asarray(order[np.searchsorted(ids, wanted, sorter=order)], dtype=np.int64)


@dataclasses.dataclass
class _Adaptation:
    """One processor's estimator, its declared configuration and the next adoption time."""

    declared: MonoSlamConfig
    estimator: TrackingNoiseEstimator = dataclasses.field(default_factory=TrackingNoiseEstimator)
    next_ns: int = -1
    adopted: int = 0
    frames: list[TrackedFrame] = dataclasses.field(default_factory=list)
    trusted: set[int] = dataclasses.field(default_factory=set)
    fitted: dict[int, tuple[int, IntArray, FloatArray]] = dataclasses.field(default_factory=dict)

    def rebuild(self, camera: CameraModel) -> None:
        """Refill the estimator from the trusted tracks' fixed-point residuals (module
        docstring); a track without new sightings keeps its fit."""
        self.estimator = TrackingNoiseEstimator()
        feed_fixed_points(self.estimator, self.frames, camera, self.trusted, self.fitted)


def adapted(
    declared: MonoSlamConfig, mode: str, estimator: TrackingNoiseEstimator
) -> MonoSlamConfig:
    """Return the configuration SLAM takes from a confident estimate (module docstring), or
    the declared one."""
    estimate = estimator.estimate()
    if not estimate.confident and mode == 'prior':  # until then, the estimator's prior
        return dataclasses.replace(
            declared, pixel_sigma_px=max(declared.pixel_sigma_px, estimate.white_px)
        )
    if not estimate.confident:
        return declared
    if mode == 'marginal':
        marginal = math.hypot(estimate.white_px, estimate.offset_px)
        return dataclasses.replace(declared, pixel_sigma_px=max(declared.pixel_sigma_px, marginal))
    relevant = estimate.offset_px**2 >= OFFSET_RELEVANCE * estimate.white_px**2
    return dataclasses.replace(
        declared,
        pixel_sigma_px=max(declared.pixel_sigma_px, estimate.white_px),
        tracking_offset_px=estimate.offset_px if relevant else declared.tracking_offset_px,
        tracking_offset_time_s=(
            estimate.offset_time_s if relevant else declared.tracking_offset_time_s
        ),
    )


def wrap(mode: str) -> None:
    """Wrap ``MonoSlamProcessor.process_frame`` so that every processor adapts (``mode``)."""
    step_frame = MonoSlamProcessor.process_frame
    states: weakref.WeakKeyDictionary[MonoSlamProcessor, _Adaptation] = weakref.WeakKeyDictionary()

    def process_frame(
        processor: MonoSlamProcessor, frame: MonoSlamFrame, frame_id: str = ''
    ) -> MonoSlamStep:
        processor.noise = None  # the study's adoption replaces the node's (estimate_noise)
        step = step_frame(processor, frame, frame_id)
        slam = processor.slam
        if slam is None:
            return step
        state = states.setdefault(processor, _Adaptation(slam.config))
        result = step.result
        if result.status == TRACKING and result.measured_ids and mode.startswith('batch'):
            assert result.centre is not None and result.rotation is not None
            state.frames.append(
                (frame.stamp_ns, result.centre, result.rotation, frame.ids, frame.pixels)
            )
            state.trusted.update(result.measured_ids)
        elif result.status == TRACKING and result.measured_ids:
            ids, predicted, _, _ = slam.predictions(frame.stamp_ns, sorted(result.measured_ids))
            residuals = frame.pixels[_rows(frame.ids, ids)] - predicted
            state.estimator.add(frame.stamp_ns, ids, residuals)
        if state.next_ns < 0:
            state.next_ns = frame.stamp_ns + ADAPT_PERIOD_NS
        if frame.stamp_ns >= state.next_ns:
            state.next_ns += ADAPT_PERIOD_NS
            if mode.startswith('batch'):
                state.rebuild(slam.camera)
            slam.config = adapted(state.declared, ADOPTION.get(mode, mode), state.estimator)
        return step

    setattr(MonoSlamProcessor, 'process_frame', process_frame)  # noqa: B010 (a study's wrapper)


def main() -> int:
    """Parse ``--adapt``, wrap, and run ``monoslam_evaluate`` with the other arguments."""
    parser = argparse.ArgumentParser(
        prog='noise_adaptation_study', description='monoslam_evaluate, SLAM adapting its noise'
    )
    parser.add_argument('--adapt', choices=MODES, default='full', help='default %(default)s')
    args, rest = parser.parse_known_args()
    wrap(args.adapt)
    return monoslam_evaluate.main(rest)


if __name__ == '__main__':
    sys.exit(main())
