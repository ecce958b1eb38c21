"""The shadow_filter's ROS-free processor: stamp pairing, the pose covariance check and
bookkeeping around ``core.shadow_filter.ShadowFilter``.

Rules: docs/design/shadow_filter_core.md."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING
from monoslam_shadow_node.common.core.inputs import CameraPose, Features
from monoslam_shadow_node.common.frame_sync import Drop, FrameSynchronizer
from monoslam_shadow_node.common.notices import Notice
from monoslam_shadow_node.shadow_filter.conversions import frame_input
from monoslam_shadow_node.shadow_filter.core.near_static import WAIT_WARNING
from monoslam_shadow_node.shadow_filter.core.shadow_decision import UNFIT_WARNING
from monoslam_shadow_node.shadow_filter.core.shadow_filter import (
    FrameResult,
    InputError,
    ShadowConfig,
    ShadowFilter,
)
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel

INPUT_WARNING = 'non-finite'
"""A core warning holding this is about bad input (logged as a warning, the rest at debug)."""
GATE_WARNING = 'outside the innovation gate'


def pose_covariance_refusal(covariance: FloatArray | None) -> str | None:
    """Return why a pose covariance (6, 6) cannot be used (an entry not finite), or None."""
    if covariance is None:
        return None
    if not np.all(np.isfinite(np.asarray(covariance, dtype=np.float64))):
        return 'pose covariance not finite'
    return None


@dataclass(frozen=True, eq=False)
class ShadowStep:
    """One processed frame: the core's result and its pose's world frame id."""

    result: FrameResult
    frame_id: str


Outcome = ShadowStep | Notice


@dataclass
class ShadowCounts:
    """Running totals of inputs, frames, drops (by ``Drop.kind``), core warnings by kind and
    classifications; ``held_*`` after the latest frame."""

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
    """Feeds paired frames to a ShadowFilter."""

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
        """Use ``camera`` from the next frame on (the first creates the filter)."""
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
        """Take back revoked features this filter handed over, as suspects; return them."""
        if self.shadow is None:
            return []
        taken = self.shadow.revoke(ids)
        self.counts.revoked_total += len(taken)
        return taken

    # --- one frame --------------------------------------------------------------------------

    def process(self, features: Features, pose: CameraPose) -> Outcome:
        """Process one frame with its pose; return the step, or the notice of a refused pose
        covariance. Raises InputError (filter unchanged), or ValueError before a camera."""
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
        """Count every drop and say it (steady states in throttled lines)."""
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
