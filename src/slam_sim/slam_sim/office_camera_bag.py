"""office_camera_sim: the EM-SAM office run seen by a camera, written as a rosbag2 mcap bag.

office_sim's run with grey images instead of observations (docs/design/simulation.md). Topics:
  /camera/image_raw/compressed (JPEG mono8, camera_optical_frame), /camera/camera_info
  /tf_static: base_link -> camera_link -> camera_optical_frame
  /odom, /ground_truth/pose, /ground_truth/landmarks: as office_sim
  /ground_truth/fiducials (slam_interfaces/FiducialArray): the markers fully visible"""

from __future__ import annotations

import argparse
import heapq
import math
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.cli import PlainTextHelpFormatter, console_main
from slam_core.geometry.quaternion import quaternion_from_rotation
from slam_core.geometry.se3 import OPTICAL_IN_LINK
from slam_core.progress import ProgressReporter
from slam_ros.qos import latched_qos, output_qos
from slam_ros.typesys import TypeRegistry
from slam_sim.core.camera_effects import CameraEffects, ImageEffects, encode_jpeg
from slam_sim.core.office import OfficeConfig, OfficeRun, Variant, simulate_office
from slam_sim.core.office_render import Renderer
from slam_sim.core.office_view import (
    DICTIONARY_NAME,
    LevelPose,
    Markers,
    MarkerTruth,
    SceneStyle,
    office_camera,
)
from slam_sim.dataset_bag import MessageFactory, TopicSpec, WrittenBag, write_bag
from slam_sim.office_bag import (
    DEFAULT_START_NS,
    OBSERVATIONS_TOPIC,
    ODOM_TOPIC,
    TOPICS,
    office_messages,
)

IMAGE_TOPIC = '/camera/image_raw/compressed'
CAMERA_INFO_TOPIC = '/camera/camera_info'
TF_STATIC_TOPIC = '/tf_static'
TRUE_FIDUCIALS_TOPIC = '/ground_truth/fiducials'
IMAGE_TYPE = 'sensor_msgs/msg/CompressedImage'
CAMERA_INFO_TYPE = 'sensor_msgs/msg/CameraInfo'
TF_TYPE = 'tf2_msgs/msg/TFMessage'
FIDUCIALS_TYPE = 'slam_interfaces/msg/FiducialArray'
IMAGE_FORMAT = 'mono8; jpeg compressed mono8'
BASE_FRAME, CAMERA_LINK, OPTICAL_FRAME = 'base_link', 'camera_link', 'camera_optical_frame'
CAMERA_FORWARD_M = 0.1
CAMERA_HEIGHT_M = 1.0
WALL_MARKER_HEIGHT_M = 1.15
DESK_MARKER_HEIGHT_M = 0.95
WALL_MOUNT_OFFSET_M = 0.01
DEFAULT_RATE_HZ = 10.0
DEFAULT_QUALITY = 65
# The camera topics (topic, type, latched); the bag also holds office_sim's TOPICS except
# /landmark_observations. At equal stamps camera messages come first, in this order.
CAMERA_TOPICS = (
    (TF_STATIC_TOPIC, TF_TYPE, True),
    (CAMERA_INFO_TOPIC, CAMERA_INFO_TYPE, False),
    (IMAGE_TOPIC, IMAGE_TYPE, False),
    (TRUE_FIDUCIALS_TOPIC, FIDUCIALS_TYPE, False),
)


@dataclass(frozen=True)
class CameraRig:
    """The camera, its rate, JPEG quality, rendering style and image effects."""

    camera: CameraModel = field(default_factory=office_camera)
    rate_hz: float = DEFAULT_RATE_HZ
    jpeg_quality: int = DEFAULT_QUALITY
    style: SceneStyle = field(default_factory=SceneStyle)
    effects: ImageEffects = field(default_factory=ImageEffects)

    def __post_init__(self) -> None:
        """Reject rates and qualities the bag cannot honour."""
        if not 0.0 < self.rate_hz <= 60.0:
            raise ValueError(f'camera rate {self.rate_hz} Hz not in (0, 60]')
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f'JPEG quality {self.jpeg_quality} not in [1, 100]')


@dataclass(frozen=True)
class CameraFrame:
    """One rendered frame: index, run stamp int ns, 8-bit image (H, W) and marker truth."""

    index: int
    stamp_ns: int
    image: np.ndarray
    truth: MarkerTruth


def frame_stamps_ns(run: OfficeRun, rate_hz: float) -> IntArray:
    """Return the camera frame stamps (F,) int ns from the run start, on the sim step grid."""
    step_ns = run.config.motion.step_ns
    times = np.arange(
        round(run.config.detector.phase_s * 1e9), run.truth.times_ns[-1] + 1, 1e9 / rate_hz
    )
    return (np.round(times / step_ns) * step_ns).astype(np.int64)


def office_markers(run: OfficeRun, stamp_ns: int) -> Markers:
    """Return the drawn markers at ``stamp_ns``: centres (L, 3) m, normals (L, 2), map frame."""
    landmarks = run.landmarks
    positions, normals = landmarks.positions_at(np.array([stamp_ns]))
    moveable = landmarks.moveable
    offset = np.where(moveable, 0.0, WALL_MOUNT_OFFSET_M)[:, None]
    height = np.where(moveable, DESK_MARKER_HEIGHT_M, WALL_MARKER_HEIGHT_M)
    drawn = moveable if run.variant == Variant.ALL_MOVEABLE else np.ones_like(moveable)
    return Markers(
        ids=landmarks.ids[drawn],
        centers_m=np.column_stack([positions[0] + offset * normals[0], height])[drawn],
        normals=normals[0][drawn],
    )


def camera_pose(base_pose: FloatArray) -> LevelPose:
    """Return the optical centre and yaw of the camera on a robot at ``base_pose`` (3,)."""
    x, y, theta = (float(v) for v in base_pose)
    position = [x + CAMERA_FORWARD_M * math.cos(theta), y + CAMERA_FORWARD_M * math.sin(theta)]
    return LevelPose(np.array([*position, CAMERA_HEIGHT_M]), theta)


def render_frames(
    run: OfficeRun, rig: CameraRig | None = None, *, end_ns: int | None = None
) -> Iterator[CameraFrame]:
    """Yield the run's camera frames up to ``end_ns`` (run time; None: all), in order."""
    rig = rig if rig is not None else CameraRig()
    renderer = Renderer(rig.camera, run.world.walls_m, rig.style)
    effects = CameraEffects(rig.effects, rig.camera, np.random.SeedSequence(run.seed).spawn(5)[4])
    stamps = frame_stamps_ns(run, rig.rate_hz)
    if end_ns is not None:
        stamps = stamps[stamps <= end_ns]
    poses = run.truth.poses_at(stamps)
    yaw_rates = run.truth.twists_at(stamps)[:, 1]
    for index, stamp in enumerate(stamps.tolist()):
        image, truth = renderer.render(camera_pose(poses[index]), office_markers(run, stamp))
        pixels = effects.apply(
            image, frame_index=index, time_s=stamp / 1e9, yaw_rate_radps=float(yaw_rates[index])
        )
        yield CameraFrame(index, stamp, pixels, truth)


class _CameraMessages:
    """Builds the camera topics' messages."""

    def __init__(self, registry: TypeRegistry, rig: CameraRig) -> None:
        self.build = MessageFactory(registry, {msgtype for _, msgtype, _ in CAMERA_TOPICS})
        self.types, self.rig = self.build.types, rig
        self.info = rig.camera.camera_info()

    def _pose(self, rotation: FloatArray, translation: FloatArray) -> Any:
        w, x, y, z = quaternion_from_rotation(rotation).tolist()
        geometry = 'geometry_msgs/msg/'
        return self.types[geometry + 'Pose'](
            position=self.types[geometry + 'Point'](
                x=float(translation[0]), y=float(translation[1]), z=float(translation[2])
            ),
            orientation=self.types[geometry + 'Quaternion'](x=x, y=y, z=z, w=w),
        )

    def tf_static(self, stamp_ns: int) -> Any:
        """Return base_link -> camera_link -> camera_optical_frame."""
        geometry = 'geometry_msgs/msg/'
        links = (
            (BASE_FRAME, CAMERA_LINK, np.eye(3), (CAMERA_FORWARD_M, 0.0, CAMERA_HEIGHT_M)),
            (CAMERA_LINK, OPTICAL_FRAME, OPTICAL_IN_LINK, (0.0, 0.0, 0.0)),
        )
        transforms = []
        for parent, child, rotation, translation in links:
            pose = self._pose(rotation, np.array(translation))
            transforms.append(
                self.types[geometry + 'TransformStamped'](
                    header=self.build.header(stamp_ns, parent),
                    child_frame_id=child,
                    transform=self.types[geometry + 'Transform'](
                        translation=self.types[geometry + 'Vector3'](
                            x=pose.position.x, y=pose.position.y, z=pose.position.z
                        ),
                        rotation=pose.orientation,
                    ),
                )
            )
        return self.types[TF_TYPE](transforms=transforms)

    def camera_info(self, stamp_ns: int) -> Any:
        """Return the CameraInfo of the rig's camera."""
        return self.build.camera_info(stamp_ns, OPTICAL_FRAME, self.info)

    def image(self, stamp_ns: int, pixels: np.ndarray) -> Any:
        """Return the JPEG CompressedImage of an 8-bit grey image."""
        data = encode_jpeg(pixels, self.rig.jpeg_quality)
        return self.types[IMAGE_TYPE](
            header=self.build.header(stamp_ns, OPTICAL_FRAME),
            format=IMAGE_FORMAT,
            data=np.frombuffer(data, dtype=np.uint8),
        )

    def fiducials(self, stamp_ns: int, truth: MarkerTruth) -> Any:
        """Return the FiducialArray of the markers the truth calls visible."""
        detection = self.types['slam_interfaces/msg/FiducialDetection']
        return self.types[FIDUCIALS_TYPE](
            header=self.build.header(stamp_ns, OPTICAL_FRAME),
            detections=[
                detection(
                    id=int(truth.ids[k]),
                    dictionary=DICTIONARY_NAME,
                    corners_px=truth.corners_px[k].reshape(8).astype(np.float64),
                    pose=self._pose(truth.rotation[k], truth.translation_m[k]),
                    pose_covariance=np.zeros(36),
                    reprojection_error_px=0.0,
                    marker_size_m=self.rig.style.side_m,
                )
                for k in np.nonzero(truth.visible)[0].tolist()
            ],
        )


def office_camera_messages(
    run: OfficeRun,
    registry: TypeRegistry,
    *,
    rig: CameraRig,
    start_ns: int,
    end_ns: int | None = None,
    progress: Callable[[float, int], None] | None = None,
) -> Iterator[tuple[str, int, Any]]:
    """Yield (topic, bag stamp ns, message) up to run time ``end_ns``; progress per frame."""
    build = _CameraMessages(registry, rig)

    def camera() -> Iterator[tuple[str, int, Any]]:
        yield TF_STATIC_TOPIC, start_ns, build.tf_static(start_ns)
        for frame in render_frames(run, rig, end_ns=end_ns):
            bag_ns = start_ns + frame.stamp_ns
            yield CAMERA_INFO_TOPIC, bag_ns, build.camera_info(bag_ns)
            yield IMAGE_TOPIC, bag_ns, build.image(bag_ns, frame.image)
            yield TRUE_FIDUCIALS_TOPIC, bag_ns, build.fiducials(bag_ns, frame.truth)
            if progress is not None:
                progress(frame.stamp_ns / 1e9, frame.index + 1)

    def office() -> Iterator[tuple[str, int, Any]]:
        for topic, bag_ns, message in office_messages(run, registry, start_ns=start_ns):
            if end_ns is not None and bag_ns > start_ns + end_ns:
                return
            if topic != OBSERVATIONS_TOPIC:
                yield topic, bag_ns, message

    yield from heapq.merge(camera(), office(), key=lambda item: item[1])


def write_office_camera_bag(
    run: OfficeRun,
    path: Path | str,
    *,
    rig: CameraRig | None = None,
    start_ns: int = DEFAULT_START_NS,
    end_s: float | None = None,
    single_file: bool = False,
    registry: TypeRegistry | None = None,
    progress: Callable[[float, int], None] | None = None,
) -> WrittenBag:
    """Write ``run`` seen by ``rig`` as an mcap bag at ``path``, up to ``end_s``."""
    rig = rig if rig is not None else CameraRig()
    registry = registry if registry is not None else TypeRegistry()
    specs = [
        (topic, msgtype, latched)
        for topic, msgtype, latched in (*TOPICS, *CAMERA_TOPICS)
        if topic != OBSERVATIONS_TOPIC
    ]
    topics = [
        TopicSpec(topic, msgtype, latched_qos() if latched else output_qos())
        for topic, msgtype, latched in specs
    ]
    end_ns = None if end_s is None else round(end_s * 1e9)
    messages = office_camera_messages(
        run, registry, rig=rig, start_ns=start_ns, end_ns=end_ns, progress=progress
    )
    return write_bag(path, topics, messages, registry=registry, single_file=single_file)


def summary(run: OfficeRun, written: WrittenBag, rig: CameraRig, elapsed_s: float) -> str:
    """Return the one-line summary of a written camera bag."""
    frames = written.counts[IMAGE_TOPIC]
    camera = rig.camera
    return (
        f'office_camera_sim: wrote {written.path} ({written.size_bytes / 1e6:.2f} MB): seed '
        f'{run.seed} variant {run.variant.value}, {frames} frames {camera.width}x'
        f'{camera.height} at {rig.rate_hz:g} Hz, JPEG quality {rig.jpeg_quality}, '
        f'{written.counts[ODOM_TOPIC]} odometry; rendered in {elapsed_s:.1f} s '
        f'({1e3 * elapsed_s / max(frames, 1):.1f} ms per frame)'
    )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='office_camera_sim',
        description=__doc__,
        formatter_class=PlainTextHelpFormatter,
    )
    parser.add_argument('--seed', type=int, required=True, help='random seed of the run')
    parser.add_argument(
        '--variant',
        default=Variant.STANDARD.value,
        choices=[v.value for v in Variant],
        help='what the moveable markers do',
    )
    parser.add_argument(
        '--output', required=True, type=Path, help='bag directory (or .mcap with --single-file)'
    )
    parser.add_argument('--single-file', action='store_true', help='write one bare .mcap file')
    parser.add_argument('--rate-hz', type=float, default=DEFAULT_RATE_HZ, help='camera rate, Hz')
    parser.add_argument('--quality', type=int, default=DEFAULT_QUALITY, help='JPEG quality, 1-100')
    parser.add_argument('--width', type=int, default=640, help='image width, px (70 deg FOV)')
    parser.add_argument('--height', type=int, default=480, help='image height, px')
    parser.add_argument('--odom-hz', type=float, default=20.0, help='odometry rate, Hz')
    parser.add_argument(
        '--duration-s', type=float, default=None, help='write only the first seconds of the run'
    )
    parser.add_argument(
        '--start-ns',
        type=int,
        default=DEFAULT_START_NS,
        help='bag time of the run start, int ns since the epoch',
    )
    return parser


@console_main('office_camera_sim')
def main(argv: list[str] | None = None) -> int:
    """Simulate one office run, render its camera images and write them as a bag."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        camera = office_camera(args.width, args.height)
    except ValueError as err:
        parser.error(f'--width/--height: {err}')
    try:
        rig = CameraRig(camera=camera, rate_hz=args.rate_hz, jpeg_quality=args.quality)
    except ValueError as err:
        parser.error(f'--rate-hz/--quality: {err}')
    if args.duration_s is not None and not args.duration_s > 0.0:
        parser.error(f'--duration-s: {args.duration_s} must be > 0')
    try:
        config = OfficeConfig(odom_rate_hz=args.odom_hz)
    except ValueError as err:
        parser.error(f'--odom-hz: {err}')
    run = simulate_office(args.seed, args.variant, config=config)
    total_s = run.duration_s if args.duration_s is None else min(args.duration_s, run.duration_s)
    reporter = ProgressReporter(total_s, label='office_camera_sim', unit='s')
    written = write_office_camera_bag(
        run,
        args.output,
        rig=rig,
        start_ns=args.start_ns,
        end_s=args.duration_s,
        single_file=args.single_file,
        progress=lambda done_s, frames: reporter.update(done_s, items=frames),
    )
    reporter.update(total_s, items=written.counts[IMAGE_TOPIC])
    reporter.finish()
    print(summary(run, written, rig, reporter.clock() - reporter.started))  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
