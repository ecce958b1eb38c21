"""What both nodes' processors take and give: extrinsics, static transforms, one frame's
output and the input error."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from marker_detector.core.base_frame import RangeBearing
from marker_detector.core.detection import MarkerDetection, Rejection

EXTRINSICS_SOURCES = ('tf_static', 'parameters')


class InputError(ValueError):
    """An input the processor cannot use now; the message names it and says why."""


@dataclass(frozen=True)
class ExtrinsicsConfig:
    """Where the camera sits on the robot: /tf_static or parameters (``detector.processor``)."""

    source: str = 'tf_static'
    base_frame: str = 'base_link'
    camera_xyz_m: tuple[float, ...] = (0.0, 0.0, 0.0)
    camera_rpy_rad: tuple[float, ...] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.source not in EXTRINSICS_SOURCES:
            raise ValueError(
                f'marker_detector setting extrinsics_source={self.source!r}: must be one of '
                f'{EXTRINSICS_SOURCES}'
            )
        if not self.base_frame:
            raise ValueError('marker_detector setting base_frame: must not be empty')
        for name, values in (
            ('camera_xyz_m', self.camera_xyz_m),
            ('camera_rpy_rad', self.camera_rpy_rad),
        ):
            if len(values) != 3 or not np.all(np.isfinite(values)):
                raise ValueError(
                    f'marker_detector setting {name}={list(values)}: must be 3 finite numbers'
                )


@dataclass
class StaticTransforms:
    """A tree of static transforms: child frame -> (parent frame, T_parent_child 4x4)."""

    parents: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)

    def add(self, parent: str, child: str, transform: np.ndarray) -> None:
        """Add or replace ``child`` in ``parent``; InputError for a self or looping transform or
        numbers that are not finite."""
        parent, child = parent.lstrip('/'), child.lstrip('/')
        if parent == child:
            raise InputError(f'static transform from {parent!r} to itself')
        matrix = np.asarray(transform, float)
        if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
            raise InputError(f'static transform {parent!r} -> {child!r}: not 4x4 finite numbers')
        ancestor = parent
        while ancestor in self.parents:
            ancestor = self.parents[ancestor][0]
            if ancestor == child:
                raise InputError(
                    f'static transform {parent!r} -> {child!r} refused: {child!r} is already '
                    f'above {parent!r}, the transforms would form a loop'
                )
        self.parents[child] = (parent, matrix)

    def _in_root(self, frame: str) -> tuple[str, np.ndarray]:
        """Return the root of ``frame``'s tree and T_root_frame (4x4)."""
        transform = np.eye(4)
        seen = {frame}
        while frame in self.parents:
            parent, parent_from_frame = self.parents[frame]
            if parent in seen:
                raise InputError(f'static transforms form a loop through {parent!r}')
            seen.add(parent)
            transform = parent_from_frame @ transform
            frame = parent
        return frame, transform

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """Return T_target_source (4x4), or None when the two frames are not connected."""
        target_root, root_from_target = self._in_root(target.lstrip('/'))
        source_root, root_from_source = self._in_root(source.lstrip('/'))
        if target_root != source_root:
            return None
        result: np.ndarray = np.linalg.inv(root_from_target) @ root_from_source
        return result


@dataclass(frozen=True)
class FrameOutput:
    """What one image gave: detections (camera frame), rejections, base-frame observations."""

    stamp_ns: int
    camera_frame: str
    base_frame: str
    detections: list[MarkerDetection]
    rejections: list[Rejection]
    observations: list[RangeBearing]
