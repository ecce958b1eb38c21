"""The monoslam node's ROS-free processor around ``core.monoslam.MonoSlam``.

Each call returns ``MonoSlamStep``s and ``Notice``s in order. Design notes:
docs/design/monoslam_core.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from monoslam_shadow_node.common.core.feature_status import STATIC
from monoslam_shadow_node.common.core.inputs import Features
from monoslam_shadow_node.common.frame_sync import Drop, StampSync, SyncNames
from monoslam_shadow_node.common.notices import Notice
from monoslam_shadow_node.monoslam.conversions import (
    HandoverInput,
    PoseFields,
    TargetSighting,
    pose_fields,
)
from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
from monoslam_shadow_node.monoslam.core.monoslam_init import MIN_KNOWN_POINTS
from monoslam_shadow_node.monoslam.core.monoslam_snapshot import (
    GapVerdict,
    gap_verdict,
    relocalise,
)
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    LOST,
    TRACKING,
    WAITING,
    MapPoint,
    MonoSlamConfig,
    MonoSlamFrame,
    MonoSlamInputError,
    MonoSlamResult,
    UpdateCounts,
    update_text,
)
from monoslam_shadow_node.monoslam.core.noise_monitor import NoiseAdaptation
from monoslam_shadow_node.monoslam.known_points_input import (
    DepthImage,
    DepthStart,
    KnownPointRows,
    assign_known_points,
)
from monoslam_shadow_node.monoslam.settings import TARGET_CORNERS
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.depth import sample_depth

SYNC_NAMES = SyncNames(
    primary='features frame',
    primary_plural='frames',
    primary_short='features',
    partner='fiducials',
    partner_plural='fiducial arrays',
    partner_topic='fiducials',
    missing_partner_kind='no_fiducials',
    missing_primary_kind='no_features',
)


def fiducials_sync(
    tolerance_ns: int, horizon_ns: int, queue_size: int, names: SyncNames = SYNC_NAMES
) -> StampSync[Features, TargetSighting]:
    """Return the pairing of features frames with the fiducials of their images.

    One detector publishes the fiducials in stamp order (``in_order_partners``): a frame waits
    for its own however far they lag, and goes without them once a later one came, or once
    ``horizon_ns`` of frames came with no fiducials at all (``stall_ns``).
    """
    return StampSync(
        tolerance_ns=tolerance_ns,
        horizon_ns=horizon_ns,
        max_entries=queue_size,
        names=names,
        in_order_partners=True,
        stall_ns=horizon_ns,
    )


STATUS_WARNINGS = ('waiting for the initialization target', 'started from', 'tracking lost')
"""The core's warnings that the state transitions report instead."""


def monoslam_frame(features: Features, sighting: TargetSighting | None) -> MonoSlamFrame:
    """Return the filter's input for one image: features, and the target's corners as keys 0-3."""
    if sighting is None or sighting.corners_px is None:
        return MonoSlamFrame(features.stamp_ns, features.ids, features.pixels)
    keys: IntArray = np.arange(TARGET_CORNERS, dtype=np.int64)
    return MonoSlamFrame(
        features.stamp_ns, features.ids, features.pixels, keys, sighting.corners_px
    )


@dataclass(frozen=True, eq=False)
class MonoSlamStep:
    """One processed frame: result, frame id, finite pose (or None), transition, gap verdict."""

    result: MonoSlamResult
    frame_id: str
    pose: PoseFields | None
    transition: str | None
    resumed: GapVerdict | None = None


Outcome = MonoSlamStep | Notice


@dataclass
class MonoSlamCounts:
    """The processor's running totals (inputs, drops by kind, handovers, losses, predictions)."""

    features_received: int = 0
    fiducials_received: int = 0
    processed: int = 0
    alone: int = 0
    skipped: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    accepted: int = 0
    refused: int = 0
    revoked: int = 0
    lost: int = 0
    resumes_predicted: int = 0
    resumes_relocalised: int = 0
    measured: int = 0
    update: UpdateCounts = field(default_factory=UpdateCounts)
    predictions: int = 0
    predictions_behind: int = 0
    depth_received: int = 0
    depth_unused: int = 0

    @property
    def dropped_total(self) -> int:
        """Inputs dropped by the pairing, all kinds."""
        return sum(self.dropped.values())


class MonoSlamProcessor:
    """Feeds paired frames to a MonoSlam filter; ``target_text`` names the target in log lines."""

    def __init__(
        self,
        config: MonoSlamConfig,
        *,
        target_text: str = 'the known points',
        map_frame: str = 'map',
        stamp_tolerance_ns: int = 0,
        sync_horizon_ns: int = 500_000_000,
        queue_size: int = 100,
        fiducials_topic: str = 'fiducials',
        camera_info_topic: str = 'camera/camera_info',
        known_rows: KnownPointRows | None = None,
        match_px: float = 3.0,
        depth_tolerance_ns: int = 20_000_000,
    ) -> None:
        self.config = config
        self.known_source = config.known_points_source
        self.known_rows = known_rows
        self.match_px = match_px
        self.assigned: dict[int, int] = {}  # track id -> known key ('file')
        self.depth_start = DepthStart(depth_tolerance_ns, sync_horizon_ns, queue_size)
        self.target_text = target_text
        self.map_frame = map_frame
        self.camera_info_topic = camera_info_topic
        self.slam: MonoSlam | None = None
        self.noise: NoiseAdaptation | None = None  # config.estimate_noise
        self.status = WAITING
        self.counts = MonoSlamCounts()
        names = dataclasses.replace(SYNC_NAMES, partner_topic=fiducials_topic)
        self.names = names
        self.sync = fiducials_sync(stamp_tolerance_ns, sync_horizon_ns, queue_size, names)
        self._predicted_ns: int | None = None
        self._asked_ns: int | None = None  # the image predictions were last asked for
        self._processed_ns: int | None = None  # the last frame given to the filter
        self._resumed = False  # the gap to the next frame is still to be judged
        self._relocalising = False
        self.resume_text = 'no'

    @property
    def waiting_features(self) -> int:
        """Feature frames waiting for their fiducials or for the camera."""
        return self.sync.waiting_primaries

    @property
    def owned_ids(self) -> frozenset[int]:
        """Track ids the filter owns (in its map now or before); empty before the camera."""
        return self.slam.owned_ids if self.slam is not None else frozenset()

    # --- streaming inputs -------------------------------------------------------------------

    def set_camera(self, camera: CameraModel) -> list[Outcome]:
        """Use ``camera`` from the next frame on (the first creates the filter); drain waiting."""
        if self.slam is None:
            if self.config.estimate_noise:
                self.noise = NoiseAdaptation(self.config, camera)
            self.slam = MonoSlam(camera, self.noise.config if self.noise else self.config)
        else:
            self.slam.set_camera(camera)
            if self.noise is not None:
                self.noise.set_camera(camera)
        return self._drain() + self._drain_direct()

    def add_features(self, features: Features) -> list[Outcome]:
        """Queue a feature frame; process what is ready."""
        self.counts.features_received += 1
        if self.known_source != 'marker':  # no fiducials to pair with
            held = self.depth_start.frames
            outcomes: list[Outcome] = []
            if len(held) == held.maxlen:
                old = held.popleft()
                text = f'features frame at stamp {old.stamp_ns} ns: queue full, dropped'
                outcomes = self._drops([Drop('queue_full', old.stamp_ns, text)])
            held.append(features)
            return outcomes + self._drain_direct()
        outcomes = self._drops(self.sync.add_primary(features))
        if self.slam is None:
            text = (
                f'no {self.camera_info_topic} received yet: holding '
                f'{self.sync.waiting_primaries} feature frame(s) until it comes'
            )
            outcomes.append(Notice('no_camera', 'warning', text, features.stamp_ns, True))
        return outcomes + self._drain()

    def add_depth(self, image: DepthImage | Callable[[], DepthImage]) -> list[Outcome]:
        """Take a depth image (or a callable decoding it) for the depth start; return outcomes."""
        self.counts.depth_received += 1
        if self.known_source != 'depth' or self.status == TRACKING:
            self.counts.depth_unused += 1
            return []
        try:
            image = image() if callable(image) else image
        except ValueError as error:
            return self._drops([Drop('bad_depth', 0, f'depth image: {error}; dropped')])
        if not self.depth_start.add_depth(image):
            text = f'depth image at stamp {image.stamp_ns} ns: not after the last; dropped'
            return self._drops([Drop('depth_out_of_order', image.stamp_ns, text)])
        return self._drain_direct()

    def _drain_direct(self, flush: bool = False) -> list[Outcome]:
        """Process the held frames that are ready ('depth' and 'file' sources)."""
        outcomes: list[Outcome] = []
        start = self.depth_start
        while self.slam is not None and start.frames:
            if self.known_source == 'file' or self.status == TRACKING:
                outcomes += self._process_direct(start.frames.popleft(), None)
                continue
            ready = start.next(flush)
            if ready is None:
                break
            features, depth = ready
            if depth is None:
                text = (f'features frame at stamp {features.stamp_ns} ns: no depth image within '
                        'the tolerance; the filter needs one to start')  # fmt: skip
                outcomes += self._drops([Drop('no_depth', features.stamp_ns, text)])
                continue
            outcomes += self._process_direct(features, depth)
        return outcomes

    def _process_direct(self, features: Features, depth: DepthImage | None) -> list[Outcome]:
        """Run a frame with its depths (a depth start) or its known points from the file."""
        assert self.slam is not None
        ids, pixels = features.ids, features.pixels
        if depth is not None:
            camera = self.slam.camera
            if depth.depth_m.shape != (camera.height, camera.width):
                text = (f'depth image at stamp {depth.stamp_ns} ns is {depth.depth_m.shape[1]}x'
                        f'{depth.depth_m.shape[0]} px, the camera {camera.width}x'
                        f'{camera.height}: it must be registered to the colour image')  # fmt: skip
                return self._drops([Drop('depth_size', depth.stamp_ns, text)])
            depths = sample_depth(depth.depth_m, pixels)
            frame = MonoSlamFrame(features.stamp_ns, ids, pixels, depths_m=depths)
            return self.process(features, None, prepared=frame)
        notices: list[Outcome] = []
        if self.known_rows is not None and not self.assigned:
            assigned = assign_known_points(self.known_rows, features, self.match_px)
            if len(assigned) >= MIN_KNOWN_POINTS:
                self.assigned = assigned
                text = (f'known points: {len(assigned)} of {len(self.known_rows.keys)} from '
                        f'the file matched tracks at stamp {features.stamp_ns} ns')  # fmt: skip
                notices.append(Notice('known_points', 'info', text, features.stamp_ns))
        known = np.array([int(i) in self.assigned for i in ids], dtype=bool)
        keys = np.array([self.assigned[int(i)] for i in ids[known]], dtype=np.int64)
        frame = MonoSlamFrame(features.stamp_ns, ids[~known], pixels[~known], keys, pixels[known])
        return notices + self.process(features, None, prepared=frame)

    def add_sighting(self, sighting: TargetSighting) -> list[Outcome]:
        """Queue the target sighting of one image (its fiducials); process what is ready."""
        self.counts.fiducials_received += 1
        return self._drops(self.sync.add_partner(sighting)) + self._drain()

    def flush(self) -> list[Outcome]:
        """The inputs stopped: frames without fiducials (or depth) go now, alone or dropped."""
        return self._drain(flush=True) + self._drain_direct(flush=True)

    def mark_moving(self, ids: Sequence[int]) -> None:
        """Note features the Shadow filter found DYNAMIC (``MonoSlam.mark_moving``)."""
        if self.slam is not None and len(ids):
            self.slam.mark_moving(ids)

    def add_handovers(self, handovers: Sequence[HandoverInput], frame_id: str) -> list[Notice]:
        """Take the Shadow filter's handovers (in ``frame_id``); return a notice per refusal."""
        notices = []
        for handover in handovers:
            reason = self.refusal(handover, frame_id)
            if reason is not None:
                notices.append(Notice('refused', 'warning', f'{reason}; refused'))
        return notices

    def refusal(self, handover: HandoverInput, frame_id: str) -> str | None:
        """Queue a handover in the filter and count it; return why it was refused, or None."""
        reason = self._refusal(handover, frame_id)
        if reason is None:
            self.counts.accepted += 1
        else:
            self.counts.refused += 1
        return reason

    def _refusal(self, handover: HandoverInput, frame_id: str) -> str | None:
        where = f'handover of feature {handover.id}'
        if self.slam is None:
            return f'{where}: no camera yet'
        if frame_id != self.map_frame:
            return f'{where}: in frame {frame_id!r}, not map_frame {self.map_frame!r}'
        if handover.status != STATIC:
            return f'{where}: status {handover.status}, not STATIC'
        return self.slam.add_handover(handover.id, handover.position, handover.covariance)

    def resume(self, slam: MonoSlam, counts: MonoSlamCounts, last_ns: int | None) -> None:
        """Continue from a checkpoint's filter, counts and last stamp (the next frame judges)."""
        self.slam, self.counts, self.status = slam, counts, slam.status
        if self.config.estimate_noise:
            self.noise = NoiseAdaptation(self.config, slam.camera)
            self.noise.resume(slam.config)
        if last_ns is not None:
            self.sync.start_after(last_ns)
        self._resumed = slam.status == TRACKING
        self.resume_text = (
            'resumed, waiting for the target' if not self._resumed else 'resumed, next frame'
        )

    def _judge_gap(self, stamp_ns: int) -> GapVerdict | None:
        """On the first frame after a resume: predict over the gap, or re-localise."""
        slam = self.slam
        verdict = gap_verdict(slam, stamp_ns) if self._resumed and slam is not None else None
        if slam is None or verdict is None:
            return None
        self._resumed = False
        if verdict.predict:
            self.counts.resumes_predicted += 1
            self.resume_text = f'predicted over {verdict.describe()}'
        else:
            self.counts.resumes_relocalised += 1
            self.resume_text = f're-localised from the target after {verdict.describe()}'
            relocalise(slam)
            self.status, self._relocalising = WAITING, True
        return verdict

    # --- one frame --------------------------------------------------------------------------

    def process_frame(self, frame: MonoSlamFrame, frame_id: str = '') -> MonoSlamStep:
        """Run one frame with associated known points; return the step. Raises the core's
        MonoSlamInputError or LinAlgError (filter unchanged), ValueError before the camera."""
        if self.slam is None:
            raise ValueError(f'no camera yet: set it (from {self.camera_info_topic}) first')
        resumed = self._judge_gap(frame.stamp_ns)
        self._processed_ns = frame.stamp_ns
        result = self.slam.process(frame)
        if self.noise is not None:
            self.noise.observe(self.slam, frame, result)
        self.counts.processed += 1
        self.counts.measured = len(result.measured_ids)
        self.counts.update = result.update
        self.counts.revoked += sum(why == 'revoked' for why in result.removed.values())
        previous, self.status = self.status, result.status
        transition = None
        if result.status == LOST:
            self.counts.lost += 1
            self.status = WAITING
            transition = 'lost'
        elif result.status == TRACKING and previous != TRACKING:
            transition = 're-initialized' if self.counts.lost else 'started'
            if self._relocalising:
                transition, self._relocalising = 're-localised', False
        return MonoSlamStep(result, frame_id, pose_fields(result), transition, resumed)

    def process(
        self,
        features: Features,
        sighting: TargetSighting | None,
        prepared: MonoSlamFrame | None = None,
    ) -> list[Outcome]:
        """Run a features frame with its sighting (None: none) or ``prepared``; return outcomes."""
        stamp_ns = features.stamp_ns
        notices: list[Outcome] = []
        if prepared is None and sighting is None:
            self.counts.alone += 1
            text = (
                f'features frame at stamp {stamp_ns} ns processed without fiducials (none with '
                f'its stamp came on {self.names.partner_topic} '
                f'{self.sync.missing_reason(stamp_ns)}); {self.counts.alone} so far'
            )
            notices.append(Notice('alone', 'warning', text, stamp_ns, True))
        elif sighting is not None and sighting.problem is not None:
            text = f'fiducials at stamp {sighting.stamp_ns} ns: {sighting.problem}; not used'
            notices.append(Notice('bad_fiducials', 'warning', text, stamp_ns))
        try:
            frame = prepared if prepared is not None else monoslam_frame(features, sighting)
            step = self.process_frame(frame, features.frame_id)
        except (MonoSlamInputError, np.linalg.LinAlgError) as err:
            self.counts.skipped += 1
            text = f'features frame at stamp {stamp_ns} ns skipped: {err}'
            return [*notices, Notice('skipped', 'error', text, stamp_ns)]
        result = step.result
        if step.resumed is not None:
            notices.append(self._resume_notice(step.resumed, stamp_ns))
        for warning in result.warnings:
            if not warning.startswith(STATUS_WARNINGS):
                text = f'frame at stamp {result.stamp_ns} ns: {warning}'
                notices.append(Notice('filter', 'warning', text, stamp_ns))
        state = self._state_notice(step, sighting)
        if state is not None:
            notices.append(state)
        if result.status == TRACKING and step.pose is None:
            text = f'pose at stamp {stamp_ns} ns is not finite (a filter fault); not published'
            notices.append(Notice('pose_not_finite', 'error', text, stamp_ns))
        return [*notices, step]

    def _resume_notice(self, verdict: GapVerdict, stamp_ns: int) -> Notice:
        if verdict.predict:
            text = (
                f'resumed from the checkpoint: predicted over {verdict.describe()}, and '
                f'measured the tracked features by their ids'
            )
            return Notice('resumed', 'info', text, stamp_ns)
        kept = len(self.slam.map_points()) if self.slam is not None else 0
        text = (
            f'resumed from the checkpoint: {verdict.describe()} is too long for the motion '
            f'model: keeping the map ({kept} points), re-localising from the target '
            f'({self.target_text}) when it is seen'
        )
        return Notice('resumed', 'warning', text, stamp_ns)

    def _state_notice(self, step: MonoSlamStep, sighting: TargetSighting | None) -> Notice | None:
        """Say the start, the loss, or (throttled) waiting for the target; None while tracking."""
        result = step.result
        stamp = f'at stamp {result.stamp_ns} ns'
        if step.transition == 'lost':
            why = next((w for w in result.warnings if w.startswith('tracking lost')), 'lost')
            text = (
                f'{why.split(";")[0]} {stamp}: re-initializing from the target '
                f'({self.target_text}) when it is seen again'
            )
            return Notice('lost', 'warning', text, result.stamp_ns)
        if step.transition is not None:
            how = next((w for w in result.warnings if w.startswith('started from')), '')
            pose = step.pose.describe() if step.pose is not None else 'pose not finite'
            text = f'{step.transition} {stamp} {how.removeprefix("started ")}: {pose}'
            return Notice(step.transition, 'info', text, result.stamp_ns)
        if result.status == TRACKING:
            return None
        return Notice('waiting', 'info', self._waiting_text(result.stamp_ns, sighting),
                      result.stamp_ns, throttle=True)  # fmt: skip

    def _waiting_text(self, stamp_ns: int, sighting: TargetSighting | None) -> str:
        target = f'initialization target ({self.target_text})'
        if self.known_source != 'marker':
            return f'waiting for the {target} at stamp {stamp_ns} ns'
        if sighting is not None and sighting.corners_px is not None:
            return (
                f'{target} seen at stamp {stamp_ns} ns, but no camera pose fits its corners '
                f'{sighting.corners_px.round(1).tolist()} (check target_size_m and the '
                'camera_info): waiting'
            )
        seen = sighting.describe_detected() if sighting is not None else 'no fiducials'
        return f'no {target} in view yet: waiting ({seen} at stamp {stamp_ns} ns)'

    def _drain(self, *, flush: bool = False) -> list[Outcome]:
        started = self.status == TRACKING
        pairs, drops = self.sync.pop(hold=self.slam is None, flush=flush, alone=started)
        outcomes = self._drops(drops)
        for features, sighting in pairs:
            outcomes += self.process(features, sighting)
        return outcomes

    def reject(self, kind: str, text: str) -> list[Outcome]:
        """Count an input the node could not read as dropped (``kind``) and say why."""
        return self._drops([Drop(kind, 0, text)])

    def _drops(self, drops: Sequence[Drop]) -> list[Outcome]:
        """Count every drop and say it once (throttled before the start)."""
        notices: list[Outcome] = []
        for drop in drops:
            self.counts.dropped[drop.kind] = self.counts.dropped.get(drop.kind, 0) + 1
            if drop.kind != self.names.missing_partner_kind:
                notices.append(Notice('dropped', 'warning', drop.text, drop.stamp_ns))
                continue
            hint = (
                ''
                if self.counts.fiducials_received
                else ' Is marker_detector running, and remapped?'
            )
            text = (
                f'{drop.text}; the filter needs the target on {self.names.partner_topic} to '
                f'start ({self.counts.dropped_total} inputs dropped so far).{hint}'
            )
            notices.append(Notice('no_fiducials', 'warning', text, drop.stamp_ns, True))
        return notices

    # --- outputs ----------------------------------------------------------------------------

    def map_points(self) -> list[MapPoint]:
        """Return the map (core ``MapPoint``s, world frame), empty before the camera."""
        return self.slam.map_points() if self.slam is not None else []

    def predictions(
        self, stamp_ns: int
    ) -> tuple[IntArray, FloatArray, FloatArray, FloatArray] | None:
        """Return ids (P,), pixels (P, 2), covariances (P, 2, 2) px^2 and warps (P, 2, 2) for the
        image at ``stamp_ns``, empty when the filter is behind; None when not due."""
        last_ns = self.sync.last_ns
        if self.slam is None or stamp_ns == self._predicted_ns:
            return None
        if last_ns is not None and stamp_ns <= last_ns:
            return None
        before, self._asked_ns = self._asked_ns, stamp_ns
        processed = self._processed_ns
        if before is not None and processed is not None and processed < before < stamp_ns:
            self.counts.predictions_behind += 1
            self._predicted_ns = stamp_ns
            nothing = np.zeros((0, 2, 2))
            return np.zeros(0, np.int64), np.zeros((0, 2)), nothing, nothing.copy()
        self._predicted_ns = stamp_ns
        self.counts.predictions += 1
        return self.slam.predictions(stamp_ns)

    def status_line(self, rate_hz: float | None = None) -> str:
        """Return the progress summary: frames, state, map, measurements, handovers, problems."""
        counts = self.counts
        rate = f' ({rate_hz:.1f}/s)' if rate_hz is not None else ''
        points = self.map_points()
        active = sum(p.active for p in points)
        handed = sum(p.source == 'handover' for p in points)
        return (
            f'{counts.processed} frames{rate}, {self.status}: map {active} active and '
            f'{len(points) - active} retired points ({handed} handed over, '
            f'{len(points) - handed} filled undecided or new), {counts.measured} features '
            f'measured in the latest frame (update: {update_text(counts.update)}); handovers '
            f'{counts.accepted} accepted, {counts.refused} refused, {counts.revoked} revoked; '
            f'lost {counts.lost} times, {counts.skipped} frames skipped, '
            f'{counts.alone} without fiducials, {counts.dropped_total} inputs dropped'
            + (f'; tracking noise {self.noise.text()}' if self.noise is not None else '')
        )
