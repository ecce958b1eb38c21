"""monoslam_image_evaluate's front end: images to ``MeasurementFrame``s with their truth.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from marker_detector.core.detection import detect_markers, make_detector
from marker_detector.core.detector_config import DetectorConfig
from monoslam_shadow_node.common.core.tracking_noise import drift_bounded_offset_px
from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig
from monoslam_shadow_node.feature_tracker.core.feature_tracker import FeatureTracker
from monoslam_shadow_node.feature_tracker.core.feature_types import Predictions
from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamFrame
from slam_core.camera import CameraModel
from slam_evaluation.monoslam_image_sources import BoolArray, FloatArray, ImageFrame
from slam_evaluation.monoslam_pipeline import MeasurementFrame, PipelineConfig
from slam_evaluation.monoslam_report import safe_ratio
from slam_sim.core.dynamic_render import LABEL_NOTHING
from slam_sim.core.init_target import InitTarget

MOVING_RADIUS_PX = 3
"""A feature with a moving object's label this close (square window, px) is moving."""


def moving_near(labels: NDArray[np.int16], pixels: FloatArray, radius_px: int) -> BoolArray:
    """Return (N,) whether a moving object's label (>= 0) lies within ``radius_px`` (square
    window, clipped at the image border) of each raw pixel (N, 2), rounded."""
    height, width = labels.shape
    centre = np.rint(np.asarray(pixels, dtype=np.float64).reshape(-1, 2)).astype(np.int64)
    offsets = np.arange(-radius_px, radius_px + 1)
    cols = np.clip(centre[:, 0, None, None] + offsets[None, None, :], 0, width - 1)
    rows = np.clip(centre[:, 1, None, None] + offsets[None, :, None], 0, height - 1)
    return np.asarray(np.any(labels[rows, cols] >= 0, axis=(1, 2)), dtype=bool)


@dataclass
class FrontEndStats:
    """Running counts of the front end (frames, features, moving flags, tracks, target
    detections) and the detected corners' errors (px)."""

    frames: int = 0
    features: int = 0
    moving: int = 0
    on_moving_label: int = 0
    on_nothing: int = 0
    tracks: int = 0
    moving_tracks: int = 0
    target_visible: int = 0
    target_detected: int = 0
    detected_and_visible: int = 0
    corner_errors_px: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """Return the counts with the derived shares and corner error statistics."""
        errors = np.array(self.corner_errors_px)
        counts = {k: v for k, v in asdict(self).items() if k != 'corner_errors_px'}
        return {
            **counts,
            'features_per_frame': safe_ratio(self.features, self.frames),
            'moving_share': safe_ratio(self.moving, self.features),
            'moving_track_share': safe_ratio(self.moving_tracks, self.tracks),
            'detection_rate': safe_ratio(self.detected_and_visible, self.target_visible),
            'detected_not_visible': self.target_detected - self.detected_and_visible,
            'corner_rms_px': float(np.sqrt(np.mean(errors**2))) if len(errors) else math.nan,
            'corner_max_px': float(errors.max()) if len(errors) else math.nan,
        }


class FrontEnd:
    """Images to SLAM frames with truth: tracker, marker detector, moving flags by labels."""

    def __init__(
        self, camera: CameraModel, target: InitTarget, target_every_n_frames: int = 1
    ) -> None:
        self.camera, self.target = camera, target
        self.target_every_n_frames = target_every_n_frames
        self.tracker = FeatureTracker(TrackerConfig())
        self.detector_config = DetectorConfig(
            dictionary=target.dictionary,
            default_marker_size_m=target.side_m,
            allowed_ids=(target.marker_id,),
        )
        self._detector = make_detector(self.detector_config)
        self._moving_ids: set[int] = set()
        self.stats = FrontEndStats()

    def declared(self, pipeline: PipelineConfig) -> PipelineConfig:
        """Return ``pipeline`` with SLAM (only) told that the tracker's offsets persist."""
        offset_px = drift_bounded_offset_px(self.tracker.config.max_drift_px)
        slam = dataclasses.replace(pipeline.slam, tracking_offset_px=offset_px)
        return dataclasses.replace(pipeline, slam=slam)

    def frame(
        self, image_frame: ImageFrame, predictions: Predictions | None = None
    ) -> MeasurementFrame:
        """Return one image's measurements (tracks, with ``predictions`` if given; the
        target's corners as known points 0-3) and its truth."""
        features = self.tracker.track(image_frame.image, predictions)
        ids, pixels = features.ids, features.pixels
        moving = self._moving(image_frame.labels, ids, pixels)
        corners = self._detect(image_frame)
        keys = np.arange(4 if corners is not None else 0, dtype=np.int64)
        known = corners if corners is not None else np.zeros((0, 2))
        stats = self.stats
        stats.frames += 1
        stats.features += len(ids)
        stats.moving += int(moving.sum())
        stats.tracks = self.tracker.next_id - 1
        stats.moving_tracks = len(self._moving_ids)
        return MeasurementFrame(
            MonoSlamFrame(image_frame.stamp_ns, ids, pixels, keys, known),
            moving,
            image_frame.rotation,
            image_frame.centre_m,
        )

    def _moving(
        self, labels: NDArray[np.int16], ids: NDArray[np.int64], pixels: FloatArray
    ) -> BoolArray:
        """Return the features' moving flags (window rule, sticky per track); count labels."""
        near = moving_near(labels, pixels, MOVING_RADIUS_PX)
        self._moving_ids.update(ids[near].tolist())
        moving = near | np.isin(ids, list(self._moving_ids))
        height, width = labels.shape
        rounded = np.clip(np.rint(pixels).astype(np.int64), 0, [width - 1, height - 1])
        own = labels[rounded[:, 1], rounded[:, 0]]
        self.stats.on_moving_label += int(np.count_nonzero(own >= 0))
        self.stats.on_nothing += int(np.count_nonzero(own == LABEL_NOTHING))
        return np.asarray(moving, dtype=bool)

    def _detect(self, image_frame: ImageFrame) -> FloatArray | None:
        """Return the target's detected raw corners (4, 2) px or None, counted against
        the truth; only every ``target_every_n_frames``-th image is searched."""
        if self.stats.frames % self.target_every_n_frames:
            return None
        result = detect_markers(
            image_frame.image, self.camera, self.detector_config, self._detector
        )
        found = [d for d in result.detections if d.id == self.target.marker_id]
        corners = np.asarray(found[0].corners_px, dtype=np.float64) if found else None
        truth = image_frame.target_corners_px
        stats = self.stats
        stats.target_visible += truth is not None
        stats.target_detected += corners is not None
        if corners is not None and truth is not None:
            stats.detected_and_visible += 1
            stats.corner_errors_px += np.linalg.norm(corners - truth, axis=1).tolist()
        return corners
