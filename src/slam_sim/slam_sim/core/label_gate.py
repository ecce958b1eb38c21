"""Paper 001's variant (a) labelled-static gate (ROS-free); see docs/design/simulation.md."""

from __future__ import annotations

import io
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import BoolArray, FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.depth import sample_depth
from slam_sim.core.depth_labels import MOVING, STATIC, UNKNOWN, PoseError
from slam_sim.core.mask_labels import MaskLabelRule, codes_at, motion_codes
from slam_sim.core.motion_masks import CodeArray, MaskedFrame

DepthMm = NDArray[np.uint16]


@dataclass(frozen=True, eq=False)
class LabelMasks:
    """Per colour image with a mask: stamps (K,) ns, codes, depths mm, poses (K, 4, 4)."""

    stamps_ns: IntArray
    codes: CodeArray
    depth_mm: DepthMm
    poses: FloatArray
    camera: CameraModel
    pose_error: PoseError

    def __post_init__(self) -> None:
        """Reject arrays that do not fit together."""
        count, shape = len(self.stamps_ns), (self.camera.height, self.camera.width)
        if self.codes.shape != (count, *shape) or self.depth_mm.shape != (count, *shape):
            raise ValueError(
                f'label masks: {count} stamps, a {shape[1]}x{shape[0]} camera, codes of shape '
                f'{self.codes.shape} and depths of shape {self.depth_mm.shape}'
            )
        if self.poses.shape != (count, 4, 4) or not np.all(np.isfinite(self.poses)):
            raise ValueError(f'label masks: poses of shape {self.poses.shape}, not finite')
        if np.any(np.diff(self.stamps_ns) <= 0):
            raise ValueError('label masks: stamps must increase')

    def index(self, stamp_ns: int, tolerance_ns: int) -> int | None:
        """Return the mask nearest ``stamp_ns`` within the tolerance, or None."""
        if not len(self.stamps_ns):
            return None
        index = int(np.searchsorted(self.stamps_ns, stamp_ns))
        near = [j for j in (index - 1, index) if 0 <= j < len(self.stamps_ns)]
        best = min(near, key=lambda j: abs(int(self.stamps_ns[j]) - stamp_ns))
        return best if abs(int(self.stamps_ns[best]) - stamp_ns) <= tolerance_ns else None

    def frame(self, index: int) -> MaskedFrame:
        """Return mask ``index`` as a MaskedFrame (depth in m, its pixel codes as the mask)."""
        depth = self.depth_mm[index].astype(np.float64) / 1000.0
        depth[self.depth_mm[index] == 0] = np.nan
        stamp = int(self.stamps_ns[index])
        return MaskedFrame(index, stamp, self.poses[index], depth, self.codes[index])


def depth_to_mm(depth_m: FloatArray) -> DepthMm:
    """Return a depth map (H, W) m, NaN where none, as millimetres (0 where none)."""
    depth = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0)
    return np.asarray(np.clip(np.rint(depth * 1000.0), 0, 65535), dtype=np.uint16)


def write_label_masks(masks: LabelMasks) -> bytes:
    """Return the compressed ``label_masks.npz`` bytes of ``masks``."""
    camera, buffer = masks.camera, io.BytesIO()
    np.savez_compressed(
        buffer,
        stamps_ns=masks.stamps_ns,
        codes=masks.codes,
        depth_mm=masks.depth_mm,
        poses=masks.poses,
        camera=np.array([camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height]),
        distortion=np.asarray(camera.D, dtype=np.float64),
        pose_error=np.array([masks.pose_error.separations_s, masks.pose_error.sigmas_m]),
    )
    return buffer.getvalue()


def read_label_masks(path: Path) -> LabelMasks:
    """Return the masks of a ``label_masks.npz``; ValueError names a file that holds none."""
    try:
        with np.load(Path(path)) as data:
            fx, fy, cx, cy, width, height = (float(v) for v in data['camera'])
            camera = CameraModel(
                int(width), int(height), np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]),
                np.asarray(data['distortion'], dtype=np.float64),
            )  # fmt: skip
            separations, sigmas = np.asarray(data['pose_error'], dtype=np.float64)
            return LabelMasks(
                np.asarray(data['stamps_ns'], dtype=np.int64),
                np.asarray(data['codes'], dtype=np.int8),
                np.asarray(data['depth_mm'], dtype=np.uint16),
                np.asarray(data['poses'], dtype=np.float64),
                camera,
                PoseError(tuple(separations.tolist()), tuple(sigmas.tolist())),
            )
    except (OSError, KeyError, ValueError, TypeError, zipfile.BadZipFile) as error:
        raise ValueError(f'{path}: not a label masks file: {error}') from error


@dataclass
class _Seen:
    """A track's last sighting at a mask: mask, pixel, depth (m, NaN: none), motion code."""

    mask: int
    pixel: FloatArray
    depth_m: float
    motion: int


@dataclass
class LabelGate:
    """Passes the tracks labelled static so far and counts."""

    masks: LabelMasks
    tolerance_ns: int = 1_000_000
    rule: MaskLabelRule = field(init=False)
    seen: dict[int, _Seen] = field(default_factory=dict)
    decided: set[int] = field(default_factory=set)
    moving: set[int] = field(default_factory=set)
    frames: int = 0
    frames_with_masks: int = 0
    features: int = 0
    passed: int = 0

    def __post_init__(self) -> None:
        """Take the labels' rule with the file's pose error; reject a negative tolerance."""
        if self.tolerance_ns < 0:
            raise ValueError(f'tolerance_ns={self.tolerance_ns!r}: must be >= 0')
        self.rule = MaskLabelRule(pose_error=self.masks.pose_error)
        self._frames: dict[int, MaskedFrame] = {}

    def admit(self, stamp_ns: int, ids: IntArray, pixels: FloatArray) -> BoolArray:
        """Take one features frame (ids (N,), raw pixels (N, 2)); return which pass."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        self.frames += 1
        self.features += len(ids)
        index = self.masks.index(int(stamp_ns), self.tolerance_ns)
        if index is not None:
            self.frames_with_masks += 1
            self._label(index, ids, pixels)
        keep = np.array([not self.withheld(int(track)) for track in ids], dtype=bool)
        self.passed += int(keep.sum())
        return keep

    def _label(self, index: int, ids: IntArray, pixels: FloatArray) -> None:
        """Give every track of a frame with mask ``index`` its sighting code."""
        here = self._mask_frame(index)
        mask = codes_at(here.mask, pixels)
        depth = sample_depth(here.depth_m, pixels, self.rule.sampling)
        motion = np.full(len(ids), UNKNOWN, dtype=np.int64)
        before = [n for n, t in enumerate(ids.tolist()) if self._seen_at(t, index - 1)]
        if before:
            previous = self._mask_frame(index - 1)
            seen = [self.seen[int(ids[n])] for n in before]
            motion[before] = motion_codes(
                self.masks.camera,
                (previous, np.array([s.pixel for s in seen]), np.array([s.depth_m for s in seen])),
                (here, pixels[before]),
                self.rule,
            )
        for n, track in enumerate(ids.tolist()):
            earlier = self.seen.get(track)
            agreed = int(motion[n])
            if agreed == MOVING and not (earlier is not None and earlier.motion == MOVING):
                agreed = UNKNOWN
            code = STATIC if STATIC in (mask[n], agreed) else UNKNOWN
            code = MOVING if MOVING in (mask[n], agreed) else code
            if code != UNKNOWN:
                self.decided.add(track)
            if code == MOVING:
                self.moving.add(track)
            self.seen[track] = _Seen(index, pixels[n].copy(), float(depth[n]), int(motion[n]))

    def _seen_at(self, track: int, index: int) -> bool:
        seen = self.seen.get(track)
        return seen is not None and seen.mask == index and np.isfinite(seen.depth_m)

    def _mask_frame(self, index: int) -> MaskedFrame:
        """Return mask ``index``'s frame, keeping the last two built."""
        if index not in self._frames:
            self._frames[index] = self.masks.frame(index)
            for old in sorted(self._frames)[:-2]:
                del self._frames[old]
        return self._frames[index]

    def withheld(self, track: int) -> bool:
        """Whether ``track`` is not labelled static so far (unknown or moving)."""
        return track not in self.decided or track in self.moving

    def tracks_moving(self) -> int:
        """The tracks labelled moving so far."""
        return len(self.moving)
