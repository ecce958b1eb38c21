"""monoslam_image_evaluate's images: a rendered Fig. 5 seed, or a ``dynamic_camera_sim`` bag."""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from marker_detector.common.conversions import camera_info_fields
from marker_detector.detector.conversions import image_from_message
from monoslam_shadow_node.common.conversions import rotation_from_quaternion
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.errors import BagError
from slam_core.images import ImageError
from slam_core.stamps import stamp_to_ns
from slam_ros.bag.source import BagSource
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_render import LABEL_NOTHING, DynamicRenderer
from slam_sim.core.dynamic_scene import DEFAULT_START_NS
from slam_sim.core.init_target import InitTarget
from slam_sim.dynamic_camera_bag import (
    CAMERA_POSE_TOPIC,
    LABELS_TOPIC,
    RAW_IMAGE_TOPIC,
    SCENE_TOPIC,
    scene_from_json,
)
from slam_sim.office_camera_bag import CAMERA_INFO_TOPIC, IMAGE_TOPIC, TRUE_FIDUCIALS_TOPIC

BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class ImageFrame:
    """One image with its truth: stamp int ns, grey image (H, W) uint8, labels (H, W) int16,
    R_world_camera (3, 3), centre (3,) m, the target's raw corners (4, 2) px or None."""

    stamp_ns: int
    image: NDArray[np.uint8]
    labels: NDArray[np.int16]
    rotation: FloatArray
    centre_m: FloatArray
    target_corners_px: FloatArray | None


@dataclass(frozen=True, eq=False)
class FrameSource:
    """One run: seed, scene config, target, camera, bag (None: rendered), image count."""

    seed: int
    config: DynamicSceneConfig
    target: InitTarget
    camera: CameraModel
    bag: Path | None
    frame_count: int

    @property
    def name(self) -> str:
        """'rendered' or the bag's path."""
        return 'rendered' if self.bag is None else str(self.bag)

    def frames(self) -> Iterator[ImageFrame]:
        """Yield the run's images with their truth, in stamp order."""
        return rendered_frames(self) if self.bag is None else bag_frames(self.bag, self.target)


def rendered_source(seed: int, config: DynamicSceneConfig) -> FrameSource:
    """Return the source that renders ``seed``'s run of ``config`` with the default target."""
    info = config.camera().camera_info()
    camera = CameraModel.from_camera_info(
        info.width, info.height, info.k, info.d, info.distortion_model
    )
    return FrameSource(seed, config, InitTarget(), camera, None, config.frame_count)


def rendered_frames(source: FrameSource) -> Iterator[ImageFrame]:
    """Yield the rendered frames of a source (frame k at DEFAULT_START_NS + k / rate)."""
    renderer = DynamicRenderer(source.config, source.seed, target=source.target)
    for index in range(source.frame_count):
        frame = renderer.render(index)
        yield ImageFrame(
            DEFAULT_START_NS + round(index * 1e9 / source.config.rate_hz),
            frame.image,
            frame.labels,
            frame.rotation,
            frame.position_m,
            frame.target_corners_px,
        )


def _image_topic(path: Path, topics: Mapping[str, Any]) -> str:
    """Return the bag's image topic; BagError naming the bag and the topics it lacks."""
    required = (SCENE_TOPIC, CAMERA_INFO_TOPIC, CAMERA_POSE_TOPIC, LABELS_TOPIC)
    missing = [topic for topic in required if topic not in topics]
    image = next((t for t in (IMAGE_TOPIC, RAW_IMAGE_TOPIC) if t in topics), None)
    if image is None:
        missing.append(f'{IMAGE_TOPIC} or {RAW_IMAGE_TOPIC}')
    if missing:
        raise BagError(
            f'bag {str(path)!r} is not a dynamic_camera_sim bag: no {", ".join(missing)} '
            '(write one with dynamic_camera_sim)'
        )
    return str(image)


def _target(path: Path, text: str) -> InitTarget:
    """Return the target described in a scene JSON's 'target' entry."""
    try:
        entry = json.loads(text)['target']
        return InitTarget(
            marker_id=int(entry['marker_id']),
            side_m=float(entry['side_m']),
            centre_m=np.asarray(entry['centre_m'], dtype=np.float64),
            rotation=np.asarray(entry['rotation'], dtype=np.float64),
            dictionary=str(entry['dictionary']),
        )
    except (KeyError, TypeError, ValueError) as err:
        raise BagError(f'bag {str(path)!r}: {SCENE_TOPIC} has no usable target: {err}') from None


def bag_source(path: Path) -> FrameSource:
    """Return the source of a dynamic_camera_sim bag; BagError naming it if missing,
    corrupt or lacking a topic."""
    with BagSource(path) as bag:
        topics = bag.topics()
        image_topic = _image_topic(path, topics)
        first: dict[str, Any] = {}
        for message in bag.messages([SCENE_TOPIC, CAMERA_INFO_TOPIC]):
            first.setdefault(
                message.topic, bag.typestore.deserialize_cdr(message.data, message.msgtype)
            )
            if len(first) == 2:
                break
    if len(first) < 2:
        absent = [t for t in (SCENE_TOPIC, CAMERA_INFO_TOPIC) if t not in first]
        raise BagError(f'bag {str(path)!r}: no message on {", ".join(absent)}')
    text = str(first[SCENE_TOPIC].data)
    info = camera_info_fields(first[CAMERA_INFO_TOPIC])
    del info['frame_id']
    try:
        seed, config = scene_from_json(text)
        camera = CameraModel.from_camera_info(**info)
    except ValueError as err:
        raise BagError(f'bag {str(path)!r}: {err}') from None
    return FrameSource(seed, config, _target(path, text), camera, path, topics[image_topic].count)


def bag_frames(path: Path, target: InitTarget) -> Iterator[ImageFrame]:
    """Yield a bag's images with truth in stamp order; BagError names bag, topic, stamp."""
    with BagSource(path) as bag:
        image_topic = _image_topic(path, bag.topics())
        wanted = (image_topic, CAMERA_POSE_TOPIC, LABELS_TOPIC, TRUE_FIDUCIALS_TOPIC)
        parts: dict[str, Any] = {}
        stamp_ns: int | None = None
        for message in bag.messages(wanted):
            if stamp_ns is not None and message.timestamp_ns != stamp_ns:
                yield _bag_frame(path, stamp_ns, parts, image_topic, target)
                parts = {}
            stamp_ns = message.timestamp_ns
            parts[message.topic] = bag.typestore.deserialize_cdr(message.data, message.msgtype)
        if stamp_ns is not None:
            yield _bag_frame(path, stamp_ns, parts, image_topic, target)


def _bag_frame(
    path: Path, stamp_ns: int, parts: Mapping[str, Any], image_topic: str, target: InitTarget
) -> ImageFrame:
    """Return the frame of one stamp's messages (image, pose, labels, true fiducials)."""
    missing = [t for t in (image_topic, CAMERA_POSE_TOPIC, LABELS_TOPIC) if t not in parts]
    if missing:
        raise BagError(f'bag {str(path)!r}: no {", ".join(missing)} at stamp {stamp_ns} ns')
    try:
        image = image_from_message(parts[image_topic])
        labels = image_from_message(parts[LABELS_TOPIC]).astype(np.int16) + LABEL_NOTHING
    except ImageError as err:
        raise BagError(f'bag {str(path)!r}: at stamp {stamp_ns} ns: {err}') from None
    pose = parts[CAMERA_POSE_TOPIC].pose
    q, p = pose.orientation, pose.position
    corners = None
    for detection in getattr(parts.get(TRUE_FIDUCIALS_TOPIC), 'detections', []):
        if int(detection.id) == target.marker_id:
            corners = np.asarray(detection.corners_px, dtype=np.float64).reshape(4, 2)
    return ImageFrame(
        stamp_to_ns(parts[image_topic].header.stamp),
        image,
        labels,
        rotation_from_quaternion(q.x, q.y, q.z, q.w),
        np.array([p.x, p.y, p.z], dtype=np.float64),
        corners,
    )
