"""dynamic_camera_sim: the dynamic scene seen by its hand-held camera, as a rosbag2 mcap bag.

dynamic_features_sim's world as grey images (docs/design/simulation.md). Topics:
  /ground_truth/scene (std_msgs/String, once, transient-local): JSON of seed and settings
  /camera/camera_info, /camera/image_raw/compressed (JPEG; --raw: /camera/image_raw mono8)
  /ground_truth/camera_pose (geometry_msgs/PoseStamped, map): the optical frame's pose
  /ground_truth/labels (PNG mono8): 0 nothing, 1 static, 2 + i moving object i
  /ground_truth/fiducials (slam_interfaces/FiducialArray): the target when fully visible"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slam_core.cli import PlainTextHelpFormatter, console_main
from slam_core.files import jsonable
from slam_core.progress import ProgressReporter
from slam_ros.qos import latched_qos, output_qos
from slam_ros.typesys import TypeRegistry
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_options import RenderOptions
from slam_sim.core.dynamic_render import LABEL_NOTHING, DynamicRenderer, RenderedFrame
from slam_sim.core.dynamic_scene import DEFAULT_START_NS
from slam_sim.core.office_view import MarkerTruth, SceneStyle
from slam_sim.dataset_bag import TopicSpec, WrittenBag, check_output, write_bag
from slam_sim.dynamic_features_bag import add_loop_argument
from slam_sim.office_camera_bag import (
    CAMERA_INFO_TOPIC,
    CAMERA_INFO_TYPE,
    FIDUCIALS_TYPE,
    IMAGE_TOPIC,
    IMAGE_TYPE,
    OPTICAL_FRAME,
    TRUE_FIDUCIALS_TOPIC,
    CameraRig,
    _CameraMessages,
)

RAW_IMAGE_TOPIC = '/camera/image_raw'
CAMERA_POSE_TOPIC = '/ground_truth/camera_pose'
LABELS_TOPIC = '/ground_truth/labels'
SCENE_TOPIC = '/ground_truth/scene'
RAW_IMAGE_TYPE = 'sensor_msgs/msg/Image'
POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
SCENE_TYPE = 'std_msgs/msg/String'
LABELS_FORMAT = 'mono8; png compressed mono8'
MAP_FRAME = 'map'
GENERATOR = 'dynamic_camera_sim'
DEFAULT_QUALITY = 65
MAX_OBJECTS = 255 + LABEL_NOTHING  # labels + 2 must fit in a byte


@dataclass(frozen=True)
class DynamicCameraBag:
    """A written dynamic camera bag: bag, seed, config, frame and visibility counts, times."""

    written: WrittenBag
    seed: int
    config: DynamicSceneConfig
    frames: int
    target_frames: int
    object_frames: tuple[int, ...]
    elapsed_s: float


def scene_json(renderer: DynamicRenderer, start_ns: int) -> str:
    """Return the JSON of ``/ground_truth/scene`` of a renderer's run."""
    target = renderer.target
    content = {
        'generator': GENERATOR,
        'seed': renderer.seed,
        'start_ns': start_ns,
        'config': dataclasses.asdict(renderer.config),
        'render': dataclasses.asdict(renderer.options),
        'target': {
            'marker_id': target.marker_id,
            'dictionary': target.dictionary,
            'side_m': target.side_m,
            'centre_m': target.centre_m,
            'rotation': target.rotation,
        },
    }
    return json.dumps(jsonable(content), sort_keys=True, allow_nan=False)


def scene_from_json(text: str) -> tuple[int, DynamicSceneConfig]:
    """Return the seed and scene config of ``/ground_truth/scene``; ValueError if not one."""
    try:
        content = json.loads(text)
        fields: dict[str, Any] = {
            key: tuple(value) if isinstance(value, list) else value
            for key, value in content['config'].items()
        }
        return int(content['seed']), DynamicSceneConfig(**fields)
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as err:
        raise ValueError(f'not a {GENERATOR} scene description: {err!r}') from None


class _Messages:
    """Builds one frame's messages (most by office_camera_sim's builder)."""

    def __init__(self, registry: TypeRegistry, renderer: DynamicRenderer, quality: int) -> None:
        target = renderer.target
        rig = CameraRig(
            camera=renderer.camera,
            rate_hz=renderer.config.rate_hz,
            jpeg_quality=quality,
            style=SceneStyle(side_m=target.side_m),
        )
        self.camera = _CameraMessages(registry, rig)
        for msgtype in (RAW_IMAGE_TYPE, POSE_TYPE, SCENE_TYPE):
            registry.ensure(msgtype)
        self.build, self.types = self.camera.build, self.camera.types
        self.target = target

    def scene(self, text: str) -> Any:
        """Return the scene description."""
        return self.types[SCENE_TYPE](data=text)

    def raw_image(self, stamp_ns: int, image: np.ndarray) -> Any:
        """Return a mono8 sensor_msgs/Image."""
        height, width = image.shape
        return self.types[RAW_IMAGE_TYPE](
            header=self.build.header(stamp_ns, OPTICAL_FRAME),
            height=height,
            width=width,
            encoding='mono8',
            is_bigendian=0,
            step=width,
            data=np.ascontiguousarray(image, dtype=np.uint8).reshape(-1),
        )

    def pose(self, stamp_ns: int, frame: RenderedFrame) -> Any:
        """Return the true optical-frame pose in map."""
        return self.types[POSE_TYPE](
            header=self.build.header(stamp_ns, MAP_FRAME),
            pose=self.camera._pose(frame.rotation, frame.position_m),
        )

    def labels(self, stamp_ns: int, frame: RenderedFrame) -> Any:
        """Return the PNG of the labels + 2."""
        ok, data = cv2.imencode('.png', (frame.labels - LABEL_NOTHING).astype(np.uint8))
        if not ok:
            raise ValueError('OpenCV could not encode the labels as PNG')
        return self.types[IMAGE_TYPE](
            header=self.build.header(stamp_ns, OPTICAL_FRAME),
            format=LABELS_FORMAT,
            data=np.asarray(data, dtype=np.uint8).reshape(-1),
        )

    def fiducials(self, stamp_ns: int, frame: RenderedFrame) -> Any:
        """Return the target's true detection if it is fully visible, else none."""
        corners = frame.target_corners_px
        rotation = frame.rotation.T @ np.asarray(self.target.rotation)
        translation = frame.rotation.T @ (self.target.centre_m - frame.position_m)
        visible = np.array([corners is not None])
        side_px = np.zeros(1)
        if corners is not None:
            side_px[0] = np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1).min()
        truth = MarkerTruth(
            ids=np.array([self.target.marker_id]),
            corners_px=np.zeros((1, 4, 2)) if corners is None else corners[None],
            rotation=rotation[None],
            translation_m=translation[None],
            in_image=visible,
            visible_fraction=visible.astype(np.float64),
            visible=visible,
            side_px=side_px,
        )
        return self.camera.fiducials(stamp_ns, truth)


@dataclass
class _Tally:
    """What the frames written so far showed."""

    frames: int = 0
    target_frames: int = 0
    object_frames: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, int))


def dynamic_camera_messages(
    renderer: DynamicRenderer,
    registry: TypeRegistry,
    *,
    quality: int = DEFAULT_QUALITY,
    raw: bool = False,
    start_ns: int = DEFAULT_START_NS,
    tally: _Tally | None = None,
    progress: Callable[[float, int], None] | None = None,
) -> Iterator[tuple[str, int, Any]]:
    """Yield (topic, bag stamp ns, message) of every frame in stamp order; progress per frame."""
    build = _Messages(registry, renderer, quality)
    config = renderer.config
    tally = tally if tally is not None else _Tally()
    tally.object_frames = np.zeros(config.objects, dtype=int)
    yield SCENE_TOPIC, start_ns, build.scene(scene_json(renderer, start_ns))
    for index, frame in enumerate(renderer.render_all(range(config.frame_count))):
        stamp_ns = start_ns + round(index * 1e9 / config.rate_hz)
        yield CAMERA_INFO_TOPIC, stamp_ns, build.camera.camera_info(stamp_ns)
        if raw:
            yield RAW_IMAGE_TOPIC, stamp_ns, build.raw_image(stamp_ns, frame.image)
        else:
            yield IMAGE_TOPIC, stamp_ns, build.camera.image(stamp_ns, frame.image)
        yield CAMERA_POSE_TOPIC, stamp_ns, build.pose(stamp_ns, frame)
        yield LABELS_TOPIC, stamp_ns, build.labels(stamp_ns, frame)
        yield TRUE_FIDUCIALS_TOPIC, stamp_ns, build.fiducials(stamp_ns, frame)
        tally.frames += 1
        tally.target_frames += frame.target_corners_px is not None
        shown = np.bincount(frame.labels[frame.labels >= 0], minlength=config.objects)
        tally.object_frames += shown[: config.objects] > 0
        if progress is not None:
            progress(frame.time_s, index + 1)


def topics(*, raw: bool = False) -> list[TopicSpec]:
    """Return the bag's topics in message order at one stamp."""
    image = (RAW_IMAGE_TOPIC, RAW_IMAGE_TYPE) if raw else (IMAGE_TOPIC, IMAGE_TYPE)
    return [
        TopicSpec(SCENE_TOPIC, SCENE_TYPE, latched_qos()),
        *(
            TopicSpec(topic, msgtype, output_qos())
            for topic, msgtype in (
                (CAMERA_INFO_TOPIC, CAMERA_INFO_TYPE),
                image,
                (CAMERA_POSE_TOPIC, POSE_TYPE),
                (LABELS_TOPIC, IMAGE_TYPE),
                (TRUE_FIDUCIALS_TOPIC, FIDUCIALS_TYPE),
            )
        ),
    ]


def _check_recordable(config: DynamicSceneConfig, quality: int) -> None:
    """Raise ValueError naming the setting a camera bag cannot hold."""
    if config.objects > MAX_OBJECTS:
        raise ValueError(f'objects = {config.objects} must be <= {MAX_OBJECTS} (8-bit labels)')
    if config.rate_hz > 60.0:
        raise ValueError(f'rate_hz = {config.rate_hz} must be <= 60 Hz (a camera)')
    if not 1 <= quality <= 100:
        raise ValueError(f'quality = {quality} must be in [1, 100]')


def write_dynamic_camera_bag(
    seed: int,
    path: Path | str,
    *,
    config: DynamicSceneConfig | None = None,
    options: RenderOptions | None = None,
    quality: int = DEFAULT_QUALITY,
    raw: bool = False,
    single_file: bool = False,
    start_ns: int = DEFAULT_START_NS,
    registry: TypeRegistry | None = None,
    progress: Callable[[float, int], None] | None = None,
) -> DynamicCameraBag:
    """Render the run of ``seed`` and ``config`` as a bag at ``path``; ValueError, BagError."""
    config = config if config is not None else DynamicSceneConfig()
    _check_recordable(config, quality)
    registry = registry if registry is not None else TypeRegistry()
    check_output(path, single_file=single_file)
    started = time.monotonic()
    renderer = DynamicRenderer(config, seed, options=options)
    tally = _Tally()
    messages = dynamic_camera_messages(
        renderer, registry, quality=quality, raw=raw, start_ns=start_ns, tally=tally,
        progress=progress,
    )  # fmt: skip
    written = write_bag(
        path, topics(raw=raw), messages, registry=registry, single_file=single_file
    )
    return DynamicCameraBag(
        written=written,
        seed=seed,
        config=config,
        frames=tally.frames,
        target_frames=tally.target_frames,
        object_frames=tuple(tally.object_frames.tolist()),
        elapsed_s=time.monotonic() - started,
    )


def summary(bag: DynamicCameraBag, *, quality: int, raw: bool) -> str:
    """Return the one-line summary of a written bag."""
    config, written = bag.config, bag.written
    kinds = [config.motions[i % len(config.motions)] for i in range(config.objects)]
    encoding = 'raw mono8' if raw else f'JPEG quality {quality}'
    return (
        f'{GENERATOR}: wrote {written.path} ({written.size_bytes / 1e6:.2f} MB): seed '
        f'{bag.seed}, {bag.frames} frames 640x480 at {config.rate_hz:g} Hz, focal '
        f'{config.focal_px:g} px, {encoding}; target fully visible in {bag.target_frames} '
        f'frames; {config.objects} objects ({", ".join(kinds) or "none"}) '
        f'in view in {", ".join(map(str, bag.object_frames)) or "no"} frames; '
        f'{bag.elapsed_s:.1f} s ({1e3 * bag.elapsed_s / max(bag.frames, 1):.1f} ms per frame)'
    )


_OPTIONS = {
    'duration_s': '--duration-s',
    'rate_hz': '--rate-hz',
    'focal_px': '--focal-px',
    'objects': '--objects',
    'hand_motion_m': '--hand-motion-m',
    'loop_away_s': '--loop-away-s',
    'quality': '--quality',
}


def _parser() -> argparse.ArgumentParser:
    defaults = DynamicSceneConfig()
    parser = argparse.ArgumentParser(
        prog=GENERATOR, description=__doc__, formatter_class=PlainTextHelpFormatter
    )
    parser.add_argument('--seed', type=int, required=True, help='random seed of the run')
    parser.add_argument(
        '--output', required=True, type=Path, help='bag directory (or .mcap with --single-file)'
    )
    parser.add_argument('--single-file', action='store_true', help='write one bare .mcap file')
    parser.add_argument(
        '--duration-s', type=float, default=defaults.duration_s, help='run length, s'
    )
    parser.add_argument(
        '--rate-hz', type=float, default=defaults.rate_hz, help='frame rate, Hz (<= 60)'
    )
    parser.add_argument(
        '--focal-px', type=float, default=defaults.focal_px, help='focal length, px (150-500)'
    )
    parser.add_argument(
        '--objects', type=int, default=defaults.objects, help='number of moving objects'
    )
    parser.add_argument(
        '--hand-motion-m',
        type=float,
        default=defaults.hand_motion_m,
        help="amplitude of the hand's sweep per axis, m (0-0.5)",
    )
    add_loop_argument(parser)
    parser.add_argument('--quality', type=int, default=DEFAULT_QUALITY, help='JPEG quality, 1-100')
    parser.add_argument('--raw', action='store_true', help='raw mono8 images instead of JPEG')
    parser.add_argument('--no-effects', action='store_true', help='no sensor noise or vignetting')
    parser.add_argument(
        '--start-ns',
        type=int,
        default=DEFAULT_START_NS,
        help='bag time of the first frame, int ns since the epoch',
    )
    return parser


def _config(parser: argparse.ArgumentParser, args: argparse.Namespace) -> DynamicSceneConfig:
    """Return the scene config of the options; a bad value exits naming its option."""
    values = {field: getattr(args, field) for field in _OPTIONS if field != 'quality'}
    try:
        config = DynamicSceneConfig(**values)
    except ValueError as err:
        field = str(err).split(' ', 1)[0]
        parser.error(f'{_OPTIONS.get(field, field)}: {err}')
    try:
        _check_recordable(config, args.quality)
    except ValueError as err:
        field = str(err).split(' ', 1)[0]
        parser.error(f'{_OPTIONS.get(field, field)}: {err}')
    return config


@console_main(GENERATOR)
def main(argv: list[str] | None = None) -> int:
    """Render one dynamic-scene run and write its images and ground truth as a bag."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    config = _config(parser, args)
    check_output(args.output, single_file=args.single_file)
    options = RenderOptions(effects=None) if args.no_effects else RenderOptions()
    reporter = ProgressReporter(config.duration_s, label=GENERATOR, unit='s')
    bag = write_dynamic_camera_bag(
        args.seed,
        args.output,
        config=config,
        options=options,
        quality=args.quality,
        raw=args.raw,
        single_file=args.single_file,
        start_ns=args.start_ns,
        progress=lambda done_s, frames: reporter.update(done_s, items=1 + 5 * frames),
    )
    reporter.update(config.duration_s, items=sum(bag.written.counts.values()))
    reporter.finish()
    print(summary(bag, quality=args.quality, raw=args.raw))  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
