"""The shadow_filter's ROS-free processor: stamp pairing, the pose covariance check and
bookkeeping around ``core.shadow_filter.ShadowFilter``.

The node hands it the camera (from camera_info), feature frames and camera poses (the
conversions' ``Features`` and ``CameraPose``); offline tools do the same, or call
``ShadowProcessor.process`` with a frame and its pose when they know the pairing. Every call
returns outcomes in the order they happened: ``ShadowStep`` (a processed frame, to publish),
and ``Notice`` (a line to log: a dropped input, a frame refused for its pose covariance or by
the core, bad pixels, filter life).

Rules:

- Pairing (``frame_sync.FrameSynchronizer``): a features frame pairs with the pose whose
  stamp is nearest within ``stamp_tolerance_ns``; pairs are processed in stamp order; a frame
  whose pose will not come (a later pose came after it; before the first pose: not within
  ``sync_horizon_ns``), or is still missing when the caller flushes because the inputs
  stopped, is dropped, as is a pose that matched no frame within ``sync_horizon_ns``. Until
  the camera is set, frames are held (the oldest dropped beyond ``queue_size``).
- Every frame with a pose is given to the filter, however uncertain the pose: the core
  adds the pose covariance to each view's ray, so an uncertain pose weakens the tests and
  delays the decisions (a feature whose ``max_tests`` tests all come before they could see
  motion stays PENDING: ``core.shadow_classifier``). There is no gate on the pose's standard
  deviations (one made SLAM and the filter lock each other out: no handover, an uncertain
  pose, no frame processed, no handover).
- The pose covariance check (``pose_covariance_refusal``): a frame whose pose covariance has
  an entry that is not finite is refused with that reason and counted (``pose_refused``), as
  a warning; the core would refuse it too, with a less specific reason. A known pose (no
  covariance) passes.
- A frame the core refuses (``InputError``: NaN pose, not a rotation, repeated ids, stamps out
  of order) is skipped with the core's reason; the filter is unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from monoslam_shadow_node.common.core.inputs import CameraPose, Features
from slam_core.arrays import FloatArray
from monoslam_shadow_node.shadow_filter.conversions import frame_input
from monoslam_shadow_node.shadow_filter.core.near_static import WAIT_WARNING
from monoslam_shadow_node.shadow_filter.core.shadow_decision import UNFIT_WARNING
from monoslam_shadow_node.shadow_filter.core.shadow_filter import (
    FrameResult,
    InputError,
    ShadowConfig,
    ShadowFilter,
)
from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING
from monoslam_shadow_node.common.frame_sync import Drop, FrameSynchronizer
from monoslam_shadow_node.common.notices import Notice
from slam_core.camera import CameraModel

INPUT_WARNING = 'non-finite'
"""A core warning holding this is about bad input (NaN pixels): logged as a warning. The
rest (gated measurements, filter restarts, tests put off) is filter life, logged at debug
level."""
GATE_WARNING = 'outside the innovation gate'


def pose_covariance_refusal(covariance: FloatArray | None) -> str | None:
    """Return why a pose covariance (6, 6) (position m, rotation rad about the world axes)
    cannot be used, or None when it can: a known pose (None) can; a covariance with an entry
    that is not finite cannot. Its size is not limited."""
    if covariance is None:
        return None
    if not np.all(np.isfinite(np.asarray(covariance, dtype=np.float64))):
        return 'pose covariance not finite'
    return None


@dataclass(frozen=True, eq=False)
class ShadowStep:
    """One processed frame: the core's result and the world frame of its pose (the outputs'
    frame id)."""

    result: FrameResult
    frame_id: str


Outcome = ShadowStep | Notice


@dataclass
class ShadowCounts:
    """Running totals: inputs received (feature frames, poses), frames processed, frames
    refused for a pose covariance that is not finite or by the core, inputs dropped by the
    pairing (by ``Drop.kind``), measurements outside the innovation gate, static fits put off
    for lying too near a camera (``near_static``), due tests whose views fixed no static
    point (``UNFIT_WARNING``), features handed over as static and called dynamic, the pending
    and dynamic features held after the latest frame, and the features SLAM revoked that came
    back here as suspects."""

    features_received: int = 0
    poses_received: int = 0
    processed: int = 0
    pose_refused: int = 0
    skipped: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    innovation_gated: int = 0
    near_waits: int = 0
    unfit: int = 0
    static_total: int = 0
    dynamic_total: int = 0
    held_pending: int = 0
    held_dynamic: int = 0
    revoked_total: int = 0

    @property
    def dropped_total(self) -> int:
        """Inputs dropped by the pairing, all kinds."""
        return sum(self.dropped.values())

    def count_result(self, result: FrameResult) -> None:
        """Add one processed frame."""
        self.processed += 1
        self.held_pending = sum(t.status == PENDING for t in result.tracks)
        self.held_dynamic = sum(t.status == DYNAMIC for t in result.tracks)
        self.static_total += len(result.handovers)
        self.dynamic_total += sum(d.status == DYNAMIC for d in result.decisions)


class ShadowProcessor:
    """Feeds paired frames to a ShadowFilter (see the module docstring)."""

    def __init__(
        self,
        config: ShadowConfig,
        *,
        stamp_tolerance_ns: int = 0,
        sync_horizon_ns: int = 1_000_000_000,
        queue_size: int = 300,
        pose_topic: str = 'monoslam/pose',
        camera_info_topic: str = 'camera/camera_info',
    ) -> None:
        self.config = config
        self.pose_topic = pose_topic
        self.camera_info_topic = camera_info_topic
        self.shadow: ShadowFilter | None = None
        self.counts = ShadowCounts()
        self.sync = FrameSynchronizer(
            tolerance_ns=stamp_tolerance_ns,
            horizon_ns=sync_horizon_ns,
            max_entries=queue_size,
            pose_topic=pose_topic,
        )
        self._dropped_waiting = 0

    @property
    def waiting_features(self) -> int:
        """Feature frames waiting for their pose or for the camera."""
        return self.sync.waiting_features

    # --- streaming inputs -------------------------------------------------------------------

    def set_camera(self, camera: CameraModel) -> list[Outcome]:
        """Use ``camera`` from the next frame on (the first one creates the filter); process
        what was waiting for it."""
        if self.shadow is None:
            self.shadow = ShadowFilter(camera, self.config)
        else:
            self.shadow.set_camera(camera)
        return self._drain()

    def add_features(self, features: Features) -> list[Outcome]:
        """Queue a feature frame; process what is ready."""
        self.counts.features_received += 1
        outcomes = self._drops(self.sync.add_features(features))
        if self.shadow is None:
            dropped = f', {self._dropped_waiting} dropped' if self._dropped_waiting else ''
            text = (
                f'no {self.camera_info_topic} received yet: holding '
                f'{self.sync.waiting_features} feature frame(s) until it comes{dropped}'
            )
            outcomes.append(Notice('no_camera', 'warning', text, features.stamp_ns, True))
        return outcomes + self._drain()

    def add_pose(self, pose: CameraPose) -> list[Outcome]:
        """Queue a camera pose; process what is ready."""
        self.counts.poses_received += 1
        return self._drops(self.sync.add_pose(pose)) + self._drain()

    def flush(self) -> list[Outcome]:
        """The inputs stopped: frames still without a pose are dropped now."""
        return self._drain(flush=True)

    def revoke(self, ids: list[int]) -> list[int]:
        """SLAM revoked these features: take back those this filter handed over (as suspects,
        ``ShadowFilter.revoke``); return them."""
        if self.shadow is None:
            return []
        taken = self.shadow.revoke(ids)
        self.counts.revoked_total += len(taken)
        return taken

    # --- one frame --------------------------------------------------------------------------

    def process(self, features: Features, pose: CameraPose) -> Outcome:
        """Process one frame with its pose; return the step, or the notice of a pose covariance
        that is not finite (the frame is refused). Raises the core's InputError (filter
        unchanged) for a frame it refuses, and ValueError before the camera is set."""
        if self.shadow is None:
            raise ValueError(f'no camera yet: set it (from {self.camera_info_topic}) first')
        refusal = pose_covariance_refusal(pose.covariance)
        if refusal is not None:
            self.counts.pose_refused += 1
            text = (
                f'frame at stamp {features.stamp_ns} ns skipped: {refusal} (pose from '
                f'{self.pose_topic})'
            )
            return Notice('pose_covariance', 'warning', text, features.stamp_ns)
        result = self.shadow.process(frame_input(features, pose))
        self.counts.count_result(result)
        return ShadowStep(result, pose.frame_id)

    def _drain(self, *, flush: bool = False) -> list[Outcome]:
        pairs, drops = self.sync.pop(hold=self.shadow is None, flush=flush)
        outcomes = self._drops(drops)
        for features, pose in pairs:
            try:
                outcome = self.process(features, pose)
            except InputError as err:
                self.counts.skipped += 1
                text = f'frame at stamp {features.stamp_ns} ns skipped: {err}'
                outcomes.append(Notice('skipped', 'error', text, features.stamp_ns))
                continue
            outcomes.append(outcome)
            if isinstance(outcome, ShadowStep):
                outcomes += self._warnings(outcome.result)
        return outcomes

    def _warnings(self, result: FrameResult) -> list[Notice]:
        """The core's warnings: bad input as warnings, filter life at debug level."""
        notices = []
        for warning in result.warnings:
            text = f'frame at stamp {result.stamp_ns} ns: {warning}'
            if INPUT_WARNING in warning:
                notices.append(Notice('input', 'warning', text, result.stamp_ns))
                continue
            self.counts.innovation_gated += GATE_WARNING in warning
            self.counts.near_waits += WAIT_WARNING in warning
            self.counts.unfit += UNFIT_WARNING in warning
            notices.append(Notice('filter', 'debug', text, result.stamp_ns))
        return notices

    def reject(self, kind: str, text: str) -> list[Outcome]:
        """Count an input the node could not read as dropped (``kind``) and say why."""
        return self._drops([Drop(kind, 0, text)])

    def _drops(self, drops: Sequence[Drop]) -> list[Outcome]:
        """Count every drop and say it once; a steady state (no camera or no pose at all yet,
        which drops every frame) is said in throttled lines instead."""
        notices: list[Outcome] = []
        for drop in drops:
            self.counts.dropped[drop.kind] = self.counts.dropped.get(drop.kind, 0) + 1
            if self.shadow is None and drop.kind == 'overflow':
                self._dropped_waiting += 1  # said in the throttled "no camera_info" line
            elif drop.kind == 'no_pose' and not self.counts.poses_received:
                text = (
                    f'no camera pose received on {self.pose_topic} at all yet: dropping '
                    f'feature frames ({self.counts.dropped_total} dropped so far, the latest '
                    f'at stamp {drop.stamp_ns} ns); is it published, and remapped?'
                )
                notices.append(Notice('no_pose_yet', 'warning', text, drop.stamp_ns, True))
            else:
                notices.append(Notice('dropped', 'warning', drop.text, drop.stamp_ns))
        return notices

    def status_line(self, rate_hz: float | None = None) -> str:
        """Return the progress summary: frames, held features, decisions, problems."""
        counts = self.counts
        rate = f' ({rate_hz:.1f}/s)' if rate_hz is not None else ''
        return (
            f'{counts.processed} frames{rate}: holding {counts.held_pending} pending and '
            f'{counts.held_dynamic} dynamic features; {counts.static_total} handed over as '
            f'static, {counts.dynamic_total} called dynamic so far; {counts.skipped} frames '
            f'skipped, {counts.pose_refused} with a non-finite pose covariance, '
            f'{counts.dropped_total} inputs dropped, {counts.innovation_gated} measurements '
            f'outside the innovation gate, {counts.near_waits} static fits too near a camera put '
            f'off, {counts.unfit} tests without a static fit; {counts.revoked_total} revoked by '
            'SLAM and taken back'
        )
