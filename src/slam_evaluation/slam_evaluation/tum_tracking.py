"""Our feature tracker over the colour images of a TUM-layout sequence, for
``tum_rgbd_sequence``: ``FeatureTracker(TrackerConfig())``, the feature tracker node's
defaults as ``monoslam_front_end.FrontEnd`` builds it, on every colour image decoded to grey
as the node decodes a CompressedImage (``marker_detector.core.images.decode_compressed``),
and each image's tracks back-projected with its depth map and pose
(``slam_sim.core.depth_labels.frame_sightings``) where it has both. Instead of running the
tracker, the tracks may be those a graph recorded (``recorded_features``: its ``/features``,
with the re-identifications SLAM's predictions brought), matched to the images by stamp."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from marker_detector.core.images import ImageError, decode_compressed
from monoslam_shadow_node.conversions import features_from_message
from monoslam_shadow_node.core.feature_config import TrackerConfig
from monoslam_shadow_node.core.feature_tracker import FeatureTracker
from slam_core.arrays import FloatArray, IntArray
from slam_core.errors import DatasetError
from slam_evaluation.classification_figure import FEATURES_TOPIC, read_messages
from slam_sim.core.depth_labels import DepthSightings, LabelRule, frame_sightings
from slam_sim.core.rgbd_depth import read_depth_m
from slam_sim.core.tum_rgbd import TumRgbd
from slam_sim.tum_rgbd_bag import image_format


@dataclass(frozen=True, eq=False)
class TrackedImages:
    """The tracker's output over all colour images: per sighting (N) the image index, track
    id and raw pixel (N, 2); the depth sightings (frames = image indices); and the colour
    images kept for the figure (index -> (H, W, 3) BGR)."""

    images: IntArray
    ids: IntArray
    pixels: FloatArray
    depth: DepthSightings
    kept: dict[int, np.ndarray] = field(default_factory=dict)


ImageTracks = tuple[IntArray, FloatArray]
"""One image's tracks: ids (N,) and raw pixels (N, 2)."""


def recorded_features(record: Path) -> dict[int, ImageTracks]:
    """Return a graph recording's ``/features`` (slam_interfaces/FeatureTrackArray) by stamp,
    ns, without pixels that are not finite. Raises DatasetError naming the recording when it
    lacks that topic."""
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
    """Run the feature tracker over every colour image (module docstring), or take each
    image's tracks from ``recorded`` (stamp ns -> features; an image without an entry has
    none), and back-project them where the image has a pose and a depth map;
    ``progress(images done)`` after each image.

    Raises:
        DatasetError: an image or depth map cannot be read or decoded, or no image's stamp
            is in ``recorded``.

    """
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
