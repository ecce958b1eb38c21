"""apriltag_bridge's ROS-free processor: apriltag_ros detections and tag transforms in,
marker_detector's range-bearing observations out. A detection array waits, in order, for the
camera model, its tags' /tf transforms at its stamp and the camera mount; ``poll`` converts
the complete ones (with ``expire`` also overdue ones, less the tags they lack).
Design notes: docs/design/marker_core.md"""

from __future__ import annotations

import math
from collections import Counter, OrderedDict, deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from marker_detector.core.base_frame import RangeBearing, to_range_bearing
from marker_detector.core.detection import MarkerDetection, Rejection
from marker_detector.core.frame_types import FrameOutput, InputError, StaticTransforms
from marker_detector.core.tag_pose import TagGates, tag_detection
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel

FAMILIES = (
    'tag16h5',
    'tag25h9',
    'tag36h11',
    'tagCircle21h7',
    'tagCircle49h12',
    'tagCustom48h12',
    'tagStandard41h12',
    'tagStandard52h13',
)
"""The family names apriltag_ros writes in AprilTagDetection.family (the library's)."""
CAMERA_MODELS = ('rectified', 'raw')
TRANSFORMS_PER_FRAME = 100
"""Stamps kept per tag frame."""
MAX_PENDING = 1000
"""Detection arrays waiting at most (the oldest is dropped beyond)."""

LOST_NO_TF = 'dropped no tag tf'
LOST_NO_CAMERA_INFO = 'dropped no camera_info'
LOST_NO_MOUNT = 'dropped no camera mount'
LOST_QUEUE_FULL = 'dropped queue full'


@dataclass(frozen=True)
class BridgeConfig:
    """What the bridge accepts and how it converts (the node's parameters)."""

    tag_family: str = 'tag36h11'
    default_marker_size_m: float = 0.16
    marker_sizes_m: Mapping[int, float] = field(default_factory=dict)
    allowed_ids: tuple[int, ...] = ()
    tag_frames: Mapping[int, str] = field(default_factory=dict)
    camera_model: str = 'rectified'
    base_frame: str = 'base_link'
    tf_wait_s: float = 0.5
    gates: TagGates = field(default_factory=TagGates)

    def __post_init__(self) -> None:
        if self.tag_family not in FAMILIES:
            raise ValueError(f'tag_family={self.tag_family!r}: must be one of {FAMILIES}')
        if self.camera_model not in CAMERA_MODELS:
            raise ValueError(f'camera_model={self.camera_model!r}: must be one of {CAMERA_MODELS}')
        if not (math.isfinite(self.default_marker_size_m) and self.default_marker_size_m > 0):
            raise ValueError(f'default_marker_size_m={self.default_marker_size_m}: must be > 0')
        for tag_id, size in self.marker_sizes_m.items():
            if not (math.isfinite(size) and size > 0):
                raise ValueError(f"marker_sizes_m=['{tag_id}:{size}']: a size must be > 0")
        if not self.base_frame:
            raise ValueError("base_frame='': must not be empty")
        if not (math.isfinite(self.tf_wait_s) and self.tf_wait_s > 0):
            raise ValueError(f'tf_wait_s={self.tf_wait_s}: must be > 0')
        names = list(self.tag_frames.values())
        if len(set(names)) != len(names) or not all(names):
            raise ValueError(
                f'tag_frames={dict(self.tag_frames)}: names must be unique and not empty'
            )

    def marker_size_m(self, tag_id: int) -> float:
        """The side of tag ``tag_id``'s black square, m."""
        return self.marker_sizes_m.get(tag_id, self.default_marker_size_m)

    def tag_frame(self, tag_id: int) -> str:
        """The frame apriltag_ros publishes tag ``tag_id``'s pose under."""
        return self.tag_frames.get(tag_id, f'{self.tag_family}:{tag_id}')

    def is_tag_frame(self, frame: str) -> bool:
        """Whether ``frame`` may be one of this family's tag frames."""
        return frame.startswith(f'{self.tag_family}:') or frame in self.tag_frames.values()


@dataclass(frozen=True, eq=False)
class Tag:
    """One entry of an AprilTagDetectionArray: family, id and corners (4, 2) px."""

    family: str
    id: int
    corners_px: FloatArray


@dataclass(frozen=True)
class Lost:
    """A tag that could not be converted: ``reason`` (a LOST_* count) and the sentence."""

    tag_id: int
    reason: str
    message: str


@dataclass(frozen=True)
class BridgeOutput:
    """One converted detection array: its FrameOutput and the tags lost."""

    frame: FrameOutput
    lost: list[Lost]


@dataclass
class _Pending:
    stamp_ns: int
    frame_id: str
    tags: list[Tag]
    received_s: float
    overdue: bool = False


class TagTransforms:
    """The latest TRANSFORMS_PER_FRAME stamps per tag frame: child -> stamp -> (parent, 4x4)."""

    def __init__(self) -> None:
        self.frames: dict[str, OrderedDict[int, tuple[str, FloatArray]]] = {}

    def add(self, parent: str, child: str, stamp_ns: int, transform: ArrayLike) -> None:
        stamps = self.frames.setdefault(child, OrderedDict())
        stamps[stamp_ns] = (parent.lstrip('/'), np.asarray(transform, dtype=np.float64))
        stamps.move_to_end(stamp_ns)
        while len(stamps) > TRANSFORMS_PER_FRAME:
            stamps.popitem(last=False)

    def at(self, child: str, stamp_ns: int) -> tuple[str, FloatArray] | None:
        """The transform to ``child`` stamped exactly ``stamp_ns`` (not interpolated), or None."""
        stamps = self.frames.get(child)
        return None if stamps is None else stamps.get(stamp_ns)

    def nearest_stamp(self, child: str, stamp_ns: int) -> int | None:
        stamps = self.frames.get(child)
        return min(stamps, key=lambda s: abs(s - stamp_ns)) if stamps else None


class AprilTagBridge:
    """Detections and transforms in, observations out."""

    def __init__(self, config: BridgeConfig) -> None:
        self.config = config
        self.camera: CameraModel | None = None
        self.static = StaticTransforms()
        self.tags = TagTransforms()
        self.pending: deque[_Pending] = deque()
        self.counts: Counter[str] = Counter()

    # -- inputs ----------------------------------------------------------------------------
    def set_camera_info(
        self,
        frame_id: str,
        width: int,
        height: int,
        k: Sequence[float],
        d: Sequence[float],
        distortion_model: str,
        p: Sequence[float],
    ) -> None:
        """Take a camera_info ('rectified': P, 'raw': K and D); InputError naming the field."""
        try:
            if self.config.camera_model == 'rectified':
                if len(p) != 12 or not (p[0] > 0 and p[5] > 0):
                    raise ValueError(f'p={list(p)}: needs fx = p[0] > 0 and fy = p[5] > 0')
                camera = CameraModel.from_intrinsics(
                    width, height, (float(p[0]), float(p[5])), (float(p[2]), float(p[6]))
                )
            else:
                camera = CameraModel.from_camera_info(width, height, k, d, distortion_model)
        except ValueError as err:
            self.counts['camera_info rejected'] += 1
            raise InputError(f'camera_info (frame {frame_id!r}) rejected: {err}') from None
        self.camera = camera

    def add_transform(self, parent: str, child: str, stamp_ns: int, transform: ArrayLike) -> None:
        """Keep a /tf transform if its child is one of the family's tag frames."""
        child = child.lstrip('/')
        if self.config.is_tag_frame(child):
            self.tags.add(parent, child, stamp_ns, transform)

    def add_detections(
        self, stamp_ns: int, frame_id: str, tags: Sequence[Tag], now_s: float
    ) -> list[str]:
        """Queue one detection array; return a warning per tag left out by family or id."""
        warnings, kept = [], []
        seen: set[int] = set()
        for tag in tags:
            if tag.family != self.config.tag_family:
                self.counts['other family'] += 1
                warnings.append(
                    f'tag {tag.family}:{tag.id} at {stamp_ns} ns ignored: tag_family is '
                    f'{self.config.tag_family!r}'
                )
            elif self.config.allowed_ids and tag.id not in self.config.allowed_ids:
                self.counts['id not allowed'] += 1
            elif tag.id in seen:
                self.counts['rejected'] += 1
                warnings.append(f'tag id {tag.id} twice at {stamp_ns} ns: the second ignored')
            else:
                seen.add(tag.id)
                kept.append(tag)
        if not kept:
            self.counts['processed'] += 1
            return warnings
        self.pending.append(_Pending(stamp_ns, frame_id, kept, now_s))
        if len(self.pending) > MAX_PENDING:
            oldest = self.pending.popleft()
            self.counts['processed'] += 1
            self._lose(LOST_QUEUE_FULL, len(oldest.tags))
            warnings.append(
                f'{len(oldest.tags)} tags at {oldest.stamp_ns} ns dropped: {MAX_PENDING} '
                'newer detection arrays wait for their transforms'
            )
        return warnings

    # -- outputs ---------------------------------------------------------------------------
    def poll(self, now_s: float, *, expire: bool = False) -> list[BridgeOutput]:
        """Convert the complete arrays at the head of the queue; with ``expire`` also those
        that waited ``tf_wait_s`` and were overdue at the previous expiring poll."""
        outputs = []
        while self.pending:
            head = self.pending[0]
            if not self._complete(head):
                if not expire or now_s - head.received_s < self.config.tf_wait_s:
                    break
                if not head.overdue:
                    head.overdue = True
                    break
            self.pending.popleft()
            outputs.append(self._convert(head))
        return outputs

    def _mount(self, camera_frame: str) -> FloatArray | None:
        return self.static.lookup(self.config.base_frame, camera_frame)

    def _complete(self, entry: _Pending) -> bool:
        if self.camera is None:
            return False
        for tag in entry.tags:
            found = self.tags.at(self.config.tag_frame(tag.id), entry.stamp_ns)
            if found is None or self._mount(found[0]) is None:
                return False
        return True

    def _convert(self, entry: _Pending) -> BridgeOutput:
        detections: list[MarkerDetection] = []
        rejections: list[Rejection] = []
        observations: list[RangeBearing] = []
        lost: list[Lost] = []
        camera_frame = entry.frame_id
        for tag in entry.tags:
            frame = self.config.tag_frame(tag.id)
            found = self.tags.at(frame, entry.stamp_ns)
            mount = None if found is None else self._mount(found[0])
            if found is None or self.camera is None or mount is None:
                lost.append(self._lost(tag, frame, entry, found))
                continue
            camera_frame = found[0]
            outcome = tag_detection(
                tag.id,
                tag.family,
                tag.corners_px,
                found[1],
                self.config.marker_size_m(tag.id),
                self.camera,
                self.config.gates,
            )
            if isinstance(outcome, MarkerDetection):
                try:
                    observations.append(to_range_bearing(outcome, mount))
                    detections.append(outcome)
                    continue
                except ValueError as err:
                    outcome = Rejection(tag.id, 'base_frame', str(err), tag.corners_px)
            rejections.append(outcome)
        self.counts['processed'] += 1
        self.counts['rejected'] += len(rejections)
        self.counts['observations'] += len(observations)
        for item in lost:
            self._lose(item.reason, 1)
        frame_output = FrameOutput(
            stamp_ns=entry.stamp_ns,
            camera_frame=camera_frame,
            base_frame=self.config.base_frame,
            detections=detections,
            rejections=rejections,
            observations=observations,
        )
        return BridgeOutput(frame_output, lost)

    def _lose(self, reason: str, count: int) -> None:
        self.counts['dropped'] += count
        self.counts[reason] += count

    def _lost(
        self, tag: Tag, frame: str, entry: _Pending, found: tuple[str, FloatArray] | None
    ) -> Lost:
        what = f'tag {frame!r} at {entry.stamp_ns} ns dropped'
        if found is None:
            nearest = self.tags.nearest_stamp(frame, entry.stamp_ns)
            seen = (
                f'its nearest transform is {(nearest - entry.stamp_ns) / 1e6:+.1f} ms away'
                if nearest is not None
                else 'no transform to it came yet'
            )
            return Lost(
                tag.id,
                LOST_NO_TF,
                f'{what}: no transform to it on /tf at that stamp within tf_wait_s '
                f'{self.config.tf_wait_s:g} s ({seen}); does apriltag_ros estimate poses '
                '(pose_estimation_method) and name the frame so (its tag.frames, our '
                'tag_frames)?',
            )
        if self.camera is None:
            return Lost(
                tag.id,
                LOST_NO_CAMERA_INFO,
                f'{what}: no usable camera_info yet; is camera/camera_info published?',
            )
        known = ', '.join(sorted(self.static.parents)) or 'none yet'
        return Lost(
            tag.id,
            LOST_NO_MOUNT,
            f'{what}: no static transform from {self.config.base_frame!r} to its camera frame '
            f'{found[0]!r} (frames on /tf_static: {known}); publish the camera mount on '
            '/tf_static',
        )
