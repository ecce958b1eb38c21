"""The closed-loop image run of the loop scene (``monoslam_loop_images``): SLAM's predictions
reach the tracker image by image, and the renderer's truth finds each track's world point."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam_evaluation.monoslam_front_end import FrontEnd
from slam_evaluation.monoslam_image_sources import rendered_source
from slam_evaluation.monoslam_loop import loop_scene
from slam_evaluation.monoslam_loop_images import (
    DUPLICATE_RADIUS_M,
    ClosedLoopFrames,
    _duplicates,
    projections,
    world_points,
)
from slam_evaluation.monoslam_pipeline import run_variant
from slam_evaluation.monoslam_runs import Settings
from slam_sim.core.dynamic_render import DynamicRenderer

FRAMES = 12


def test_slam_predicts_each_image_and_the_truth_finds_the_tracks_points(tmp_path: Path) -> None:
    """The first images of a rendered loop: once SLAM has started (on the target, in the
    first image), every image is tracked with its predictions; each track's world point
    projects back onto the pixel it was first seen at and is in view there."""
    settings = Settings((2,), 20.0, ('c',), tmp_path)
    source = rendered_source(2, loop_scene(settings, False, 6.0))
    images = []
    for image in source.frames():
        images.append(image)
        if len(images) == FRAMES:
            break
    advanced = []
    frames = ClosedLoopFrames(
        images, FrontEnd(source.camera, source.target), lambda: advanced.append(1)
    )
    record = run_variant('c', frames, source.camera, settings.pipeline(source.target),
                         attach=frames.attach)  # fmt: skip
    assert len(advanced) == FRAMES and len(frames.frames) == FRAMES
    assert not record.lost_frames and np.all(np.isfinite(record.centres))
    # SLAM starts on the target in the first image and maps features from the next on:
    # every image after that is tracked with predictions
    assert frames.predicted >= FRAMES - 3
    renderer = DynamicRenderer(source.config, source.seed, target=source.target)
    first = frames.frames[0].measurements
    points = world_points(renderer, frames.first_seen, first.ids.tolist())
    assert len(points) >= 0.9 * len(first.ids)  # no movers: all on the static scene
    ids = sorted(points)
    visible, pixels = projections(renderer, FRAMES, np.array([points[i] for i in ids]), 11.0)
    for column, track_id in enumerate(ids):
        pixel = first.pixels[first.ids.tolist().index(track_id)]
        assert np.linalg.norm(pixels[0, column] - pixel) < 0.01
    assert visible[0].mean() >= 0.9  # the border band and occluded corners aside


def test_duplicates_are_points_closer_than_the_radius() -> None:
    base = np.array([1.0, 2.0, 3.0])
    points = {
        1: base,
        2: base + np.array([0.5 * DUPLICATE_RADIUS_M, 0.0, 0.0]),  # the same point again
        3: base + np.array([0.1, 0.0, 0.0]),
    }
    assert _duplicates(points) == 1
    assert _duplicates({1: base, 3: points[3]}) == 0
