"""The loop scene from rendered images, closed loop, with truth from the renderer.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Any, overload

import numpy as np

from monoslam_shadow_node.feature_tracker.core.feature_types import Predictions
from monoslam_shadow_node.monoslam.core.monoslam_model import beyond_fold
from monoslam_shadow_node.monoslam.processor import MonoSlamProcessor
from slam_evaluation.monoslam_front_end import FrontEnd
from slam_evaluation.monoslam_image_sources import FloatArray, FrameSource, ImageFrame
from slam_evaluation.monoslam_loop import (
    REMATCH_FRAMES,
    LoopRun,
    loop_frames,
    rematch_metrics,
    trajectory_metrics,
)
from slam_evaluation.monoslam_pipeline import MeasurementFrame, VariantRecord, run_variant
from slam_evaluation.monoslam_runs import Settings
from slam_sim.core.dynamic_render import LABEL_STATIC, DynamicRenderer

REID_TOLERANCE_PX = 3.0
"""A re-matched feature must be measured within this distance of its world point's
projection (3 sigma of a 1 px tracking error); farther, it is another point."""
OCCLUSION_TOLERANCE = 0.02
"""A point is occluded when the scene along its pixel is nearer than (1 - this) x its depth
(the probe's depth and the projection's agree to far better than 2 %)."""
DUPLICATE_RADIUS_M = 0.02
"""Two tracks whose world points are this close are the same surface point: the tracker
keeps tracks min_distance_px (10 px, 10 cm at 3 m) apart, so distinct ones are farther."""


class ClosedLoopFrames(Sequence[MeasurementFrame]):
    """The run's images through the front end, each tracked with the SLAM processor's
    predictions (``attach`` before the first image)."""

    def __init__(
        self, images: Sequence[ImageFrame], front_end: FrontEnd, advance: Callable[[], None]
    ) -> None:
        self.images, self.front_end, self.advance = images, front_end, advance
        self.slam: MonoSlamProcessor | None = None
        self.frames: list[MeasurementFrame] = []
        self.first_seen: dict[int, tuple[int, FloatArray]] = {}  # id -> (image, pixel)
        self.predicted = 0  # images tracked with predictions

    def attach(self, slam: MonoSlamProcessor) -> None:
        """Take SLAM's predictions from ``slam`` from the next image on."""
        self.slam = slam

    def __len__(self) -> int:
        return len(self.images)

    @overload
    def __getitem__(self, index: int) -> MeasurementFrame: ...

    @overload
    def __getitem__(self, index: slice) -> Sequence[MeasurementFrame]: ...

    def __getitem__(self, index: int | slice) -> MeasurementFrame | Sequence[MeasurementFrame]:
        return self.frames[index]

    def __iter__(self) -> Iterator[MeasurementFrame]:
        if self.frames:
            yield from self.frames
            return
        for index, image in enumerate(self.images):
            predictions = None
            predicted = None if self.slam is None else self.slam.predictions(image.stamp_ns)
            if predicted is not None and len(predicted[0]):  # SLAM has a map to predict
                predictions = Predictions(*predicted)
                self.predicted += 1
            frame = self.front_end.frame(image, predictions)
            measured = frame.measurements
            for track_id, pixel in zip(measured.ids.tolist(), measured.pixels, strict=True):
                self.first_seen.setdefault(track_id, (index, pixel.copy()))
            self.frames.append(frame)
            self.advance()
            yield frame


def run_image_loop(
    settings: Settings,
    source: FrameSource,
    images: Sequence[ImageFrame],
    variant: str,
    movers: bool,
    advance: Callable[[], None],
) -> LoopRun:
    """Run ``variant`` closed loop over a loop scene's ``images`` (of ``source``)."""
    front_end = FrontEnd(source.camera, source.target)
    frames = ClosedLoopFrames(images, front_end, advance)
    pipeline = front_end.declared(settings.pipeline(source.target))
    record = run_variant(variant, frames, source.camera, pipeline, attach=frames.attach)
    metrics = image_loop_metrics(source, frames, record)
    metrics['images_predicted'] = frames.predicted
    metrics['front_end'] = frames.front_end.stats.summary()
    return LoopRun(source.seed, movers, variant, source.config, frames.frames, record, metrics)


def world_points(
    renderer: DynamicRenderer,
    first_seen: Mapping[int, tuple[int, FloatArray]],
    ids: Iterable[int],
) -> dict[int, FloatArray]:
    """Return the world points (3,) m of the static tracks ``ids`` from their first sight
    (``first_seen``: id -> (image index, raw pixel))."""
    camera = renderer.camera
    by_image: dict[int, list[int]] = {}
    for track_id in ids:
        if track_id in first_seen:
            by_image.setdefault(first_seen[track_id][0], []).append(track_id)
    out: dict[int, FloatArray] = {}
    for index, group in by_image.items():
        pixels = np.array([first_seen[i][1] for i in group])
        depths, labels = renderer.probe(index, pixels)
        rays, _ = camera.pixel_rays(pixels)
        rotation, centre = renderer.pose(index)
        for k, track_id in enumerate(group):
            if labels[k] == LABEL_STATIC and math.isfinite(float(depths[k])):
                out[track_id] = centre + rotation @ (rays[k] * depths[k])
    return out


def projections(
    renderer: DynamicRenderer, count: int, points: FloatArray, reach_px: float
) -> tuple[np.ndarray, FloatArray]:
    """Return per image (first ``count``) and point whether in view (K, N) and the true raw
    pixel (K, N, 2) (NaN behind the camera or past the fold)."""
    camera = renderer.camera
    visible = np.zeros((count, len(points)), dtype=bool)
    pixels = np.full((count, len(points), 2), np.nan)
    if not len(points):
        return visible, pixels
    for index in range(count):
        rotation, centre = renderer.pose(index)
        local = (points - centre) @ rotation
        front = (local[:, 2] > 0.0) & ~beyond_fold(camera, local)
        if not np.any(front):
            continue
        pixels[index, front] = camera.project(local[front])
        u, v = pixels[index, :, 0], pixels[index, :, 1]
        with np.errstate(invalid='ignore'):
            inside = front & (u >= reach_px) & (u <= camera.width - 1 - reach_px)
            inside &= (v >= reach_px) & (v <= camera.height - 1 - reach_px)
        rows = np.flatnonzero(inside)
        if len(rows):
            depths, _ = renderer.probe(index, pixels[index, rows])
            visible[index, rows] = depths >= local[rows, 2] * (1.0 - OCCLUSION_TOLERANCE)
    return visible, pixels


def comebacks(visible: np.ndarray, marks: dict[str, int]) -> Iterator[tuple[int, int]]:
    """Yield (column, entry image) of the points of ``visible`` (K, N) that left the view
    while away and came back after the turn back."""
    for column in range(visible.shape[1]):
        seen = visible[:, column]
        if seen[marks['away'] : marks['return']].all():
            continue  # never left the view
        entry = next(
            (k for k in range(marks['return'], len(seen)) if seen[k] and not seen[k - 1]), None
        )
        if entry is not None:
            yield column, entry


def image_loop_metrics(
    source: FrameSource, frames: ClosedLoopFrames, record: VariantRecord
) -> dict[str, Any]:
    """Return the metrics of one closed-loop image run (module docstring)."""
    scene = source.config
    marks, rate = loop_frames(scene), round(scene.rate_hz)
    renderer = DynamicRenderer(scene, source.seed, target=source.target)
    before = range(max(0, marks['start'] - rate), marks['start'] + 1)
    mapped = sorted(set().union(*(record.measured_ids[k] for k in before)))
    points = world_points(renderer, frames.first_seen, mapped)
    ids = sorted(points)
    config = frames.front_end.tracker.config
    reach = max(config.border_margin_px, config.lk_window_px / 2.0)
    count = len(frames.frames)
    visible, true_pixels = projections(
        renderer, count, np.array([points[i] for i in ids]).reshape(-1, 3), reach
    )
    returned = wrong = 0
    entries: list[int] = []
    for column, entry in comebacks(visible, marks):
        track_id = ids[column]
        returned += 1
        for k in range(entry, min(entry + REMATCH_FRAMES + 1, count)):
            if track_id not in record.measured_ids[k]:
                continue
            measured = frames.frames[k].measurements
            pixel = measured.pixels[measured.ids.tolist().index(track_id)]
            if float(np.linalg.norm(pixel - true_pixels[k, column])) <= REID_TOLERANCE_PX:
                entries.append(k)
            else:
                wrong += 1
            break
    map_ids = [p.id for p in record.map_points]
    duplicates = _duplicates(world_points(renderer, frames.first_seen, map_ids))
    return {
        **rematch_metrics(len(mapped), returned, entries, len(record.map_points), duplicates),
        'with_truth': len(ids),
        'wrong': wrong,
        **trajectory_metrics(record, frames.frames, marks, rate),
    }


def _duplicates(points: dict[int, FloatArray]) -> int:
    """Return how many of the points lie within DUPLICATE_RADIUS_M of an earlier one."""
    kept: list[FloatArray] = []
    duplicates = 0
    for track_id in sorted(points):
        point = points[track_id]
        if any(float(np.linalg.norm(point - other)) < DUPLICATE_RADIUS_M for other in kept):
            duplicates += 1
        else:
            kept.append(point)
    return duplicates
