"""Our feature tracker (or a recording's tracks) over a TUM-layout sequence's images.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from monoslam_shadow_node.common.conversions import features_from_message
from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig
from monoslam_shadow_node.feature_tracker.core.feature_tracker import FeatureTracker
from slam_core.arrays import FloatArray, IntArray
from slam_core.errors import DatasetError
from slam_core.images import ImageError, decode_compressed
from slam_evaluation.classification_figure import FEATURES_TOPIC, read_messages
from slam_sim.core.depth_labels import DepthSightings, LabelRule, frame_sightings
from slam_sim.core.rgbd_depth import read_depth_m
from slam_sim.core.tum_rgbd import TumRgbd
from slam_sim.tum_rgbd_bag import image_format


@dataclass(frozen=True, eq=False)
class TrackedImages:
    """The tracks: image index, id and raw pixel (N, 2) per sighting; depth sightings; the
    figure's colour images (index -> (H, W, 3) BGR)."""

    images: IntArray
    ids: IntArray
    pixels: FloatArray
    depth: DepthSightings
    kept: dict[int, np.ndarray] = field(default_factory=dict)


ImageTracks = tuple[IntArray, FloatArray]
"""One image's tracks: ids (N,) and raw pixels (N, 2)."""


def recorded_features(record: Path) -> dict[int, ImageTracks]:
    """Return a recording's ``/features`` by stamp ns; DatasetError if it lacks the topic."""
    out: dict[int, ImageTracks] = {}
    try:
        messages = read_messages(record, [FEATURES_TOPIC], FEATURES_TOPIC)
    except ValueError as err:
        raise DatasetError(f'--tracks: {err}') from None
    for _, message in messages:
        features = features_from_message(message)
        finite = np.all(np.isfinite(features.pixels), axis=1)
        out[features.stamp_ns] = features.ids[finite], features.pixels[finite]
    return out


def track_images(
    sequence: TumRgbd,
    rule: LabelRule,
    *,
    keep: tuple[int, ...] = (),
    progress: Callable[[int], None] | None = None,
    recorded: Mapping[int, ImageTracks] | None = None,
) -> TrackedImages:
    """Track every colour image (or take ``recorded``'s tracks) and back-project them;
    DatasetError for an unreadable image or no stamp in ``recorded``."""
    tracker = FeatureTracker(TrackerConfig())
    images, ids, pixels, depth, kept = [], [], [], [], {}
    nothing: ImageTracks = (np.zeros(0, np.int64), np.zeros((0, 2)))
    if recorded is not None and not set(recorded) & set(sequence.stamps_ns.tolist()):
        raise DatasetError(f'{sequence.directory}: no image stamp matches a recorded frame')
    for index, path in enumerate(sequence.rgb.files):
        data = path.read_bytes() if recorded is None or index in keep else b''
        if recorded is not None:
            found_ids, found_pixels = recorded.get(int(sequence.stamps_ns[index]), nothing)
        else:
            try:
                gray = decode_compressed(image_format(data), data)
            except ImageError as err:
                raise DatasetError(f'{path}: {err}') from None
            features = tracker.track(gray)
            found_ids, found_pixels = features.ids, features.pixels
        images.append(np.full(len(found_ids), index, dtype=np.int64))
        ids.append(found_ids)
        pixels.append(found_pixels)
        if sequence.has_pose[index] and sequence.depth_index[index] >= 0:
            depth_path = sequence.depth.files[sequence.depth_index[index]]
            depth_m = read_depth_m(depth_path, sequence.depth_units_per_m)
            frame = (index, int(sequence.stamps_ns[index]))
            depth.append(
                frame_sightings(
                    sequence.camera, frame, found_ids, found_pixels, depth_m,
                    sequence.poses[index], rule,
                )
            )  # fmt: skip
        if index in keep:
            colour = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
            if colour is None:
                raise DatasetError(f'{path}: cannot be decoded as a colour image')
            kept[index] = np.asarray(colour)
        if progress is not None:
            progress(index + 1)
    return TrackedImages(
        np.concatenate(images), np.concatenate(ids), np.vstack(pixels),
        DepthSightings.concatenate(depth), kept,
    )  # fmt: skip
