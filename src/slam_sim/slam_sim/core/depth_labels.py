"""Moving/static labels of tracks from depth maps and poses; see docs/design/simulation.md."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slam_core.arrays import BoolArray, FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.depth import DepthSampling, depth_sigma_m, sample_depth
from slam_core.lazy_stats import chi2
from slam_sim.core.rgbd_depth import camera_points, world_points

MOVING, STATIC, UNKNOWN = 1, 0, -1
LABEL_NAMES = {MOVING: 'moving', STATIC: 'static', UNKNOWN: 'unknown'}


@dataclass(frozen=True)
class PoseError:
    """The ground truth's per-axis position error sigma_pose (m) per pose separation (s)."""

    separations_s: tuple[float, ...] = (0.0,)
    sigmas_m: tuple[float, ...] = (0.07,)

    def __post_init__(self) -> None:
        """Reject tables that cannot be interpolated."""
        separations = np.asarray(self.separations_s, dtype=np.float64)
        sigmas = np.asarray(self.sigmas_m, dtype=np.float64)
        if not len(separations) or separations.shape != sigmas.shape:
            raise ValueError('pose error: give as many sigmas as separations, at least one')
        if np.any(np.diff(separations) <= 0) or not np.all(np.isfinite(separations)):
            raise ValueError(f'pose error separations {self.separations_s}: must increase')
        if not np.all(np.isfinite(sigmas) & (sigmas >= 0)):
            raise ValueError(f'pose error sigmas {self.sigmas_m}: must be finite and >= 0 m')

    @classmethod
    def constant(cls, sigma_m: float) -> PoseError:
        """Return the same sigma (m) at every separation."""
        return cls((0.0,), (float(sigma_m),))

    def at(self, separation_s: float) -> float:
        """Return sigma_pose (m) for two poses ``separation_s`` apart."""
        return float(np.interp(abs(separation_s), self.separations_s, self.sigmas_m))


@dataclass(frozen=True)
class LabelRule:
    """The depth label rule's settings (pixel noise px, pose error, probability, ends)."""

    pixel_sigma_px: float = 1.0
    pose_error: PoseError = field(default_factory=PoseError)
    probability: float = 0.9973
    ends: int = 3
    sampling: DepthSampling = field(default_factory=DepthSampling)

    def __post_init__(self) -> None:
        """Reject values the rule cannot use, naming the field."""
        if not self.pixel_sigma_px >= 0.0:
            raise ValueError(f'pixel_sigma_px={self.pixel_sigma_px}: must be >= 0 px')
        if not 0.0 < self.probability < 1.0:
            raise ValueError(f'probability={self.probability}: must be in (0, 1)')
        if self.ends < 1:
            raise ValueError(f'ends={self.ends}: must be >= 1')

    @property
    def bound(self) -> float:
        """The chi-square bound with 3 degrees of freedom at ``probability``."""
        return float(chi2.ppf(self.probability, 3))


@dataclass(frozen=True, eq=False)
class DepthSightings:
    """Depth sightings (S): ids, frames, stamps ns, points (S, 3) m, covariances (S, 3, 3)."""

    ids: IntArray
    frames: IntArray
    stamps_ns: IntArray
    points: FloatArray
    covariances: FloatArray

    @classmethod
    def empty(cls) -> DepthSightings:
        """Return no sightings."""
        nothing = np.zeros(0, np.int64)
        return cls(nothing, nothing, nothing, np.zeros((0, 3)), np.zeros((0, 3, 3)))

    @classmethod
    def concatenate(cls, parts: list[DepthSightings]) -> DepthSightings:
        """Return the sightings of ``parts`` one after the other."""
        if not parts:
            return cls.empty()
        return cls(
            np.concatenate([p.ids for p in parts]),
            np.concatenate([p.frames for p in parts]),
            np.concatenate([p.stamps_ns for p in parts]),
            np.concatenate([p.points for p in parts]),
            np.concatenate([p.covariances for p in parts]),
        )

    def select(self, keep: BoolArray) -> DepthSightings:
        """Return the sightings where ``keep`` (S,) is true."""
        return DepthSightings(
            self.ids[keep],
            self.frames[keep],
            self.stamps_ns[keep],
            self.points[keep],
            self.covariances[keep],
        )


def frame_sightings(
    camera: CameraModel,
    frame: tuple[int, int],
    ids: IntArray,
    pixels: FloatArray,
    depth_m: FloatArray,
    pose: FloatArray,
    rule: LabelRule,
) -> DepthSightings:
    """Return one frame's depth sightings of ids (N,) at raw pixels (N, 2), depth (H, W) m."""
    depth = sample_depth(depth_m, pixels, rule.sampling)
    local = camera_points(camera, pixels, depth)
    keep = np.all(np.isfinite(local), axis=1)
    local, z = local[keep], depth[keep]
    rays = local / z[:, None]
    covariance = (depth_sigma_m(z) ** 2)[:, None, None] * np.einsum('ni,nj->nij', rays, rays)
    covariance[:, 0, 0] += (z * rule.pixel_sigma_px / camera.fx) ** 2
    covariance[:, 1, 1] += (z * rule.pixel_sigma_px / camera.fy) ** 2
    rotation = pose[:3, :3]
    covariance = rotation @ covariance @ rotation.T
    count = int(keep.sum())
    return DepthSightings(
        np.asarray(ids, dtype=np.int64)[keep],
        np.full(count, frame[0], dtype=np.int64),
        np.full(count, frame[1], dtype=np.int64),
        world_points(pose, local),
        covariance,
    )


@dataclass(frozen=True, eq=False)
class TrackLabels:
    """Labels of tracks (T): ids, codes (MOVING 1, STATIC 0, UNKNOWN -1), statistics."""

    ids: IntArray
    labels: IntArray
    statistics: FloatArray
    depth_sightings: IntArray

    def counts(self) -> dict[str, int]:
        """Return the counts: moving, static, unknown, and unknown with no or one sighting."""
        unknown = self.labels == UNKNOWN
        return {
            'tracks': len(self.ids),
            'moving': int(np.count_nonzero(self.labels == MOVING)),
            'static': int(np.count_nonzero(self.labels == STATIC)),
            'unknown': int(np.count_nonzero(unknown)),
            'unknown_no_depth': int(np.count_nonzero(unknown & (self.depth_sightings == 0))),
            'unknown_one_depth': int(np.count_nonzero(unknown & (self.depth_sightings == 1))),
        }

    def moving_share(self) -> float:
        """Return the share of labelled tracks labelled moving (NaN for none)."""
        labelled = np.count_nonzero(self.labels != UNKNOWN)
        if not labelled:
            return float('nan')
        return float(np.count_nonzero(self.labels == MOVING) / labelled)

    def moving_by_id(self) -> dict[int, bool]:
        """Return id -> moving of the labelled tracks (unknown ones left out)."""
        known = self.labels != UNKNOWN
        moving = self.labels[known] == MOVING
        return {int(i): bool(m) for i, m in zip(self.ids[known], moving, strict=True)}

    def label_of(self, ids: IntArray) -> IntArray:
        """Return the label codes (N,) of track ids (N,) (UNKNOWN for ids not listed)."""
        ids = np.asarray(ids, dtype=np.int64)
        out = np.full(len(ids), UNKNOWN, dtype=np.int64)
        if not len(self.ids):
            return out
        position = np.clip(np.searchsorted(self.ids, ids), 0, len(self.ids) - 1)
        found = self.ids[position] == ids
        out[found] = self.labels[position[found]]
        return out


def label_tracks(track_ids: IntArray, sightings: DepthSightings, rule: LabelRule) -> TrackLabels:
    """Return the labels of ``track_ids`` (any order, repeats allowed) from their sightings."""
    ids = np.unique(np.asarray(track_ids, dtype=np.int64))
    labels = np.full(len(ids), UNKNOWN, dtype=np.int64)
    statistics = np.full(len(ids), np.nan)
    counts = np.zeros(len(ids), dtype=np.int64)
    order = np.lexsort((sightings.frames, sightings.ids))
    sorted_ids = sightings.ids[order]
    starts = np.searchsorted(sorted_ids, ids, side='left')
    stops = np.searchsorted(sorted_ids, ids, side='right')
    bound = rule.bound
    for index, (start, stop) in enumerate(zip(starts.tolist(), stops.tolist(), strict=True)):
        rows = order[start:stop]
        counts[index] = len(rows)
        if len(rows) < 2:
            continue
        k = min(rule.ends, len(rows) // 2)
        head, tail = rows[:k], rows[-k:]
        difference = np.median(sightings.points[tail], axis=0)
        difference -= np.median(sightings.points[head], axis=0)
        separation_s = (
            float(np.median(sightings.stamps_ns[tail]) - np.median(sightings.stamps_ns[head]))
            / 1e9
        )
        covariance = sightings.covariances[head].mean(axis=0)
        covariance = covariance + sightings.covariances[tail].mean(axis=0)
        covariance += 2.0 * rule.pose_error.at(separation_s) ** 2 * np.eye(3)
        statistic = float(difference @ np.linalg.solve(covariance, difference))
        statistics[index] = statistic
        labels[index] = MOVING if statistic > bound else STATIC
    return TrackLabels(ids, labels, statistics, counts)
