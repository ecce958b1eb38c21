"""Moving/static labels of tracks from motion masks; see docs/design/simulation.md."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import cv2
import numpy as np

from slam_core.arrays import BoolArray, FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.depth import DepthSampling, depth_sigma_m, sample_depth
from slam_core.lazy_stats import chi2
from slam_sim.core.depth_labels import MOVING, STATIC, UNKNOWN, PoseError, TrackLabels
from slam_sim.core.motion_masks import CodeArray, MaskedFrame
from slam_sim.core.rgbd_depth import camera_points, in_camera, world_points


@dataclass(frozen=True)
class MaskLabelRule:
    """The mask label rule's settings: moving share, disc radius px, gap, motion test."""

    share: float = 0.5
    radius_px: int = 4
    max_gap_images: int = 1
    pixel_sigma_px: float = 1.0
    pose_error: PoseError = field(default_factory=PoseError)
    probability: float = 0.9973
    sampling: DepthSampling = field(default_factory=DepthSampling)

    def __post_init__(self) -> None:
        """Reject values the rule cannot use, naming the field."""
        if not 0.0 < self.share <= 1.0:
            raise ValueError(f'share={self.share}: must be in (0, 1]')
        if not 0 <= self.radius_px <= 32:
            raise ValueError(f'radius_px={self.radius_px}: must be in [0, 32]')
        if self.max_gap_images < 0:
            raise ValueError(f'max_gap_images={self.max_gap_images}: must be >= 0')
        if not self.pixel_sigma_px >= 0.0:
            raise ValueError(f'pixel_sigma_px={self.pixel_sigma_px}: must be >= 0 px')
        if not 0.0 < self.probability < 1.0:
            raise ValueError(f'probability={self.probability}: must be in (0, 1)')

    @property
    def bound(self) -> float:
        """The motion test's chi-square bound with 2 degrees of freedom."""
        return float(chi2.ppf(self.probability, 2))


@dataclass(frozen=True, eq=False)
class TrackSightings:
    """A tracker's sightings (N): image, id, raw pixel (N, 2), velocity (N, 2) px/image."""

    images: IntArray
    ids: IntArray
    pixels: FloatArray
    velocities: FloatArray

    @classmethod
    def of(cls, images: IntArray, ids: IntArray, pixels: FloatArray) -> TrackSightings:
        """Return the sightings with their velocities (N, 2) px per image."""
        images = np.asarray(images, dtype=np.int64)
        ids = np.asarray(ids, dtype=np.int64)
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        order = np.lexsort((images, ids))
        step = np.full((len(ids), 2), np.nan)
        follows = (np.diff(ids[order]) == 0) & (np.diff(images[order]) == 1)
        change = np.diff(pixels[order], axis=0)
        step[order[1:][follows]] = change[follows]  # from the previous image
        backward = order[:-1][follows]
        missing = np.isnan(step[backward, 0])
        step[backward[missing]] = change[follows][missing]  # from the next image
        return cls(images, ids, pixels, step)

    def at_image(self, image: int, max_gap_images: int) -> tuple[IntArray, FloatArray]:
        """Return the tracks (K,) seen within ``max_gap_images`` of ``image``, pixels (K, 2)."""
        gap = np.abs(self.images - image)
        near = np.flatnonzero(gap <= max_gap_images)
        near = near[np.lexsort((gap[near], self.ids[near]))]
        first = np.ones(len(near), bool)
        first[1:] = np.diff(self.ids[near]) != 0
        near = near[first]
        offset = (image - self.images[near]).astype(np.float64)
        velocity = np.where(offset[:, None] == 0.0, 0.0, self.velocities[near])
        pixels = self.pixels[near] + velocity * offset[:, None]
        known = np.all(np.isfinite(pixels), axis=1)
        return self.ids[near][known], pixels[known]


def pixel_codes(frame: MaskedFrame, radius_px: int) -> CodeArray:
    """Return the code (H, W) a sighting gets at each pixel of a mask's image."""
    mask, depth = frame.mask, frame.depth_m
    nearest_moving = _nearest_depth(mask, depth, MOVING, radius_px)
    nearest_static = _nearest_depth(mask, depth, STATIC, radius_px)
    around = np.where(np.isfinite(nearest_static), STATIC, UNKNOWN)
    around = np.where(
        np.isfinite(nearest_moving) & (nearest_moving <= nearest_static), MOVING, around
    )
    return np.asarray(np.where(mask == UNKNOWN, around, mask), dtype=np.int8)


def codes_at(codes: CodeArray, pixels: FloatArray) -> IntArray:
    """Return ``pixel_codes``' codes (N,) at raw pixels (N, 2); UNKNOWN outside."""
    height, width = codes.shape
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    found = np.full(len(pixels), UNKNOWN, dtype=np.int64)
    finite = np.all(np.isfinite(pixels), axis=1)
    spot = np.zeros((len(pixels), 2), dtype=np.int64)
    spot[finite] = np.rint(pixels[finite]).astype(np.int64)
    inside = finite & (spot[:, 0] >= 0) & (spot[:, 0] < width)
    inside &= (spot[:, 1] >= 0) & (spot[:, 1] < height)
    found[inside] = codes[spot[inside, 1], spot[inside, 0]]
    return found


def sighting_codes(frame: MaskedFrame, pixels: FloatArray, radius_px: int) -> IntArray:
    """Return the mask's codes (N,) at raw pixels (N, 2), UNKNOWN ones from the nearest surface."""
    return codes_at(pixel_codes(frame, radius_px), pixels)


def _nearest_depth(mask: CodeArray, depth_m: FloatArray, code: int, radius_px: int) -> FloatArray:
    """Return the nearest depth (H, W) m of ``code`` pixels within ``radius_px``, else inf."""
    source = np.where((mask == code) & np.isfinite(depth_m), depth_m, np.inf).astype(np.float32)
    if radius_px == 0:
        return source.astype(np.float64)
    size = 2 * radius_px + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    return np.asarray(cv2.erode(source, kernel, borderType=cv2.BORDER_REPLICATE), np.float64)


@dataclass(frozen=True, eq=False)
class MaskSightings:
    """Mask sightings (S): ids, images, combined codes, mask codes and motion codes."""

    ids: IntArray
    images: IntArray
    codes: IntArray
    mask_codes: IntArray
    motion_codes: IntArray

    def select(self, keep: BoolArray) -> MaskSightings:
        """Return the sightings where ``keep`` (S,) is true."""
        return MaskSightings(
            self.ids[keep],
            self.images[keep],
            self.codes[keep],
            self.mask_codes[keep],
            self.motion_codes[keep],
        )

    def depth_only(self) -> MaskSightings:
        """Return the sightings with the masks' codes alone (the motion codes UNKNOWN)."""
        unknown = np.full(len(self.ids), UNKNOWN, dtype=np.int64)
        return MaskSightings(self.ids, self.images, self.mask_codes, self.mask_codes, unknown)


@dataclass(frozen=True, eq=False)
class _FrameSightings:
    """One mask's sightings (K): ids ascending, pixels (K, 2), robust depths (K,) m."""

    frame: MaskedFrame
    ids: IntArray
    pixels: FloatArray
    depth_m: FloatArray


def motion_codes(
    camera: CameraModel,
    first: tuple[MaskedFrame, FloatArray, FloatArray],
    second: tuple[MaskedFrame, FloatArray],
    rule: MaskLabelRule,
) -> IntArray:
    """Return the motion codes (K,) of K tracks from mask k to mask j."""
    (frame_k, pixels_k, depth_k), (frame_j, pixels_j) = first, second
    codes = np.full(len(pixels_k), UNKNOWN, dtype=np.int64)
    local = camera_points(camera, pixels_k, depth_k)
    farther = camera_points(camera, pixels_k, depth_k + depth_sigma_m(depth_k))
    seen = in_camera(frame_j.pose, world_points(frame_k.pose, local))
    seen_far = in_camera(frame_j.pose, world_points(frame_k.pose, farther))
    usable = np.all(np.isfinite(seen), axis=1) & (seen[:, 2] > 0.1) & (seen_far[:, 2] > 0.1)
    if not np.any(usable):
        return codes
    predicted = camera.project(seen[usable])
    shift = camera.project(seen_far[usable]) - predicted
    residual = pixels_j[usable] - predicted
    dt_s = abs(frame_j.stamp_ns - frame_k.stamp_ns) / 1e9
    sigma_pose = rule.pose_error.at(dt_s)
    covariance = np.einsum('ni,nj->nij', shift, shift)
    z = seen[usable, 2]
    covariance[:, 0, 0] += 2.0 * rule.pixel_sigma_px**2 + 2.0 * (camera.fx * sigma_pose / z) ** 2
    covariance[:, 1, 1] += 2.0 * rule.pixel_sigma_px**2 + 2.0 * (camera.fy * sigma_pose / z) ** 2
    statistic = np.einsum(
        'ni,ni->n', residual, np.linalg.solve(covariance, residual[..., None])[..., 0]
    )
    codes[usable] = np.where(statistic > rule.bound, MOVING, STATIC)
    return codes


def mask_sightings(
    camera: CameraModel,
    tracks: TrackSightings,
    frames: Iterable[MaskedFrame],
    rule: MaskLabelRule,
    coded: Callable[[MaskedFrame, CodeArray], None] | None = None,
) -> MaskSightings:
    """Return every track's mask sighting at every mask, in mask order."""
    parts: list[tuple[IntArray, IntArray, IntArray, IntArray]] = []
    previous: _FrameSightings | None = None
    for frame in frames:
        frame_codes = pixel_codes(frame, rule.radius_px)
        if coded is not None:
            coded(frame, frame_codes)
        track_ids, pixels = tracks.at_image(frame.image, rule.max_gap_images)
        order = np.argsort(track_ids)
        track_ids, pixels = track_ids[order], pixels[order]
        here = _FrameSightings(
            frame, track_ids, pixels, sample_depth(frame.depth_m, pixels, rule.sampling)
        )
        if previous is not None:
            parts[-1][3][:] = _motion_to(camera, previous, here, rule)
        parts.append(
            (
                track_ids,
                np.full(len(track_ids), frame.image, dtype=np.int64),
                codes_at(frame_codes, pixels),
                np.full(len(track_ids), UNKNOWN, dtype=np.int64),
            )
        )
        previous = here
    if not parts:
        nothing = np.zeros(0, dtype=np.int64)
        return MaskSightings(nothing, nothing, nothing, nothing, nothing)
    ids, images, mask, motion = (np.concatenate(column) for column in zip(*parts, strict=True))
    motion = _agreeing(ids, motion)
    codes = np.where((mask == STATIC) | (motion == STATIC), STATIC, UNKNOWN)
    codes = np.where((mask == MOVING) | (motion == MOVING), MOVING, codes)
    return MaskSightings(ids, images, codes, mask, motion)


def _agreeing(ids: IntArray, motion: IntArray) -> IntArray:
    """Return the motion codes (S,) with each unconfirmed MOVING made UNKNOWN."""
    order = np.argsort(ids, kind='stable')  # per track, in mask order
    moving = motion[order] == MOVING
    same = ids[order][1:] == ids[order][:-1]
    joined = np.zeros(len(order), bool)
    joined[1:] |= same & moving[:-1]
    joined[:-1] |= same & moving[1:]
    out = motion.copy()
    out[order[moving & ~joined]] = UNKNOWN
    return out


def _motion_to(
    camera: CameraModel, first: _FrameSightings, second: _FrameSightings, rule: MaskLabelRule
) -> IntArray:
    """Return the motion codes (K,) of ``first``'s tracks to ``second`` (UNKNOWN if not in it)."""
    codes = np.full(len(first.ids), UNKNOWN, dtype=np.int64)
    _, in_first, in_second = np.intersect1d(
        first.ids, second.ids, assume_unique=True, return_indices=True
    )
    codes[in_first] = motion_codes(
        camera,
        (first.frame, first.pixels[in_first], first.depth_m[in_first]),
        (second.frame, second.pixels[in_second]),
        rule,
    )
    return codes


def label_by_masks(
    track_ids: IntArray, sightings: MaskSightings, rule: MaskLabelRule
) -> TrackLabels:
    """Return the labels of ``track_ids`` (any order, repeats allowed) from mask sightings."""
    ids = np.unique(np.asarray(track_ids, dtype=np.int64))
    decided = sightings.codes != UNKNOWN
    listed = np.isin(sightings.ids, ids) & decided
    position = np.searchsorted(ids, sightings.ids[listed])
    moving = np.bincount(
        position, weights=sightings.codes[listed] == MOVING, minlength=len(ids)
    ).astype(np.int64)
    count = np.bincount(position, minlength=len(ids)).astype(np.int64)
    share = np.full(len(ids), np.nan)
    seen = count > 0
    share[seen] = moving[seen] / count[seen]
    labels = np.full(len(ids), UNKNOWN, dtype=np.int64)
    labels[seen] = np.where(share[seen] >= rule.share, MOVING, STATIC)
    return TrackLabels(ids, labels, share, count)
