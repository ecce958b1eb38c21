"""tum_rgbd_import: a TUM-layout RGB-D sequence (TUM RGB-D, Bonn) as a rosbag2 mcap bag.

Topics at the dataset's stamps (docs/design/simulation.md):
  /camera/camera_info; /camera/image_raw/compressed: the colour files' bytes (--raw: bgr8)
  /camera/depth/image_raw (sensor_msgs/Image 16UC1 mm, at the depth stamps; --no-depth)
  /ground_truth/camera_pose (geometry_msgs/PoseStamped, map): optical frame, interpolated
Example: tum_rgbd_import --dataset ../shared/data/bonn_crowd --convention bonn
  --output out/bonn_crowd/bonn_crowd.mcap --single-file"""

from __future__ import annotations

import argparse
import heapq
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slam_core.cli import PlainDescriptionHelpFormatter, console_main
from slam_core.errors import DatasetError
from slam_core.geometry.quaternion import quaternion_from_rotation
from slam_core.progress import ProgressReporter
from slam_ros.qos import output_qos
from slam_ros.typesys import TypeRegistry
from slam_sim.core.tum_rgbd import (
    DEFAULT_MAX_GAP_NS,
    DEFAULT_TOLERANCE_NS,
    DEPTH_UNITS_PER_M,
    INTRINSICS_PRESETS,
    POSE_CONVENTIONS,
    Intrinsics,
    TumRgbd,
    read_tum_rgbd,
)
from slam_sim.dataset_bag import MessageFactory, TopicSpec, WrittenBag, check_output, write_bag
from slam_sim.dynamic_camera_bag import (
    CAMERA_POSE_TOPIC,
    MAP_FRAME,
    POSE_TYPE,
    RAW_IMAGE_TOPIC,
    RAW_IMAGE_TYPE,
)
from slam_sim.office_camera_bag import (
    CAMERA_INFO_TOPIC,
    CAMERA_INFO_TYPE,
    IMAGE_TOPIC,
    IMAGE_TYPE,
    OPTICAL_FRAME,
)

PROG = 'tum_rgbd_import'
DEPTH_TOPIC = '/camera/depth/image_raw'
PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'


@dataclass(frozen=True)
class TumRgbdBag:
    """A written bag: the bag (path, counts, size), the sequence and the seconds spent."""

    written: WrittenBag
    sequence: TumRgbd
    elapsed_s: float


def depth_millimetres(raw: np.ndarray, units_per_m: float) -> np.ndarray:
    """Return a 16-bit depth map (H, W) as uint16 mm, rounded, clipped; 0 stays 0."""
    millimetres = np.rint(raw.astype(np.float64) * (1000.0 / units_per_m))
    return np.clip(millimetres, 0, np.iinfo(np.uint16).max).astype(np.uint16)


def image_format(data: bytes) -> str:
    """Return 'png' for PNG bytes, else 'jpeg' (CompressedImage.format)."""
    return 'png' if data.startswith(PNG_SIGNATURE) else 'jpeg'


class _Messages:
    """Builds the bag's messages."""

    def __init__(self, registry: TypeRegistry, sequence: TumRgbd) -> None:
        self.build = MessageFactory(
            registry, (CAMERA_INFO_TYPE, IMAGE_TYPE, RAW_IMAGE_TYPE, POSE_TYPE)
        )
        self.types = self.build.types
        self.info = sequence.camera.camera_info()
        self.units_per_m = sequence.depth_units_per_m

    def camera_info(self, stamp_ns: int) -> Any:
        """Return the CameraInfo of the sequence's camera."""
        return self.build.camera_info(stamp_ns, OPTICAL_FRAME, self.info)

    def compressed(self, stamp_ns: int, data: bytes) -> Any:
        """Return a CompressedImage of the file bytes as stored."""
        return self.types[IMAGE_TYPE](
            header=self.build.header(stamp_ns, OPTICAL_FRAME),
            format=image_format(data),
            data=np.frombuffer(data, dtype=np.uint8),
        )

    def image(self, stamp_ns: int, pixels: np.ndarray, encoding: str) -> Any:
        """Return a sensor_msgs/Image of (H, W, 3) uint8 bgr8 or (H, W) uint16 16UC1."""
        height, width = pixels.shape[:2]
        data = np.ascontiguousarray(pixels)
        return self.types[RAW_IMAGE_TYPE](
            header=self.build.header(stamp_ns, OPTICAL_FRAME),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=int(sys.byteorder == 'big'),
            step=data.strides[0],
            data=data.view(np.uint8).reshape(-1),
        )

    def pose(self, stamp_ns: int, transform: np.ndarray) -> Any:
        """Return the PoseStamped in map of T_world_camera (4, 4)."""
        geometry = 'geometry_msgs/msg/'
        w, x, y, z = quaternion_from_rotation(transform[:3, :3]).tolist()
        position = transform[:3, 3]
        return self.types[POSE_TYPE](
            header=self.build.header(stamp_ns, MAP_FRAME),
            pose=self.types[geometry + 'Pose'](
                position=self.types[geometry + 'Point'](
                    x=float(position[0]), y=float(position[1]), z=float(position[2])
                ),
                orientation=self.types[geometry + 'Quaternion'](x=x, y=y, z=z, w=w),
            ),
        )


def _read(path: Path, flags: int) -> np.ndarray:
    image = cv2.imread(str(path), flags)
    if image is None:
        raise DatasetError(f'{path}: cannot be read as an image')
    return np.asarray(image)


def tum_rgbd_messages(
    sequence: TumRgbd,
    registry: TypeRegistry,
    *,
    raw: bool = False,
    depth: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> Iterator[tuple[str, int, Any]]:
    """Yield (topic, bag stamp ns, message) in stamp order; progress per colour image."""
    build = _Messages(registry, sequence)
    events = [(int(s), 0, k) for k, s in enumerate(sequence.rgb.stamps_ns)]
    if depth:
        events += [(int(s), 1, k) for k, s in enumerate(sequence.depth.stamps_ns)]
    heapq.heapify(events)
    count = 0
    while events:
        stamp, kind, index = heapq.heappop(events)
        if kind == 1:
            raw_depth = _read(sequence.depth.files[index], cv2.IMREAD_UNCHANGED)
            if raw_depth.ndim != 2 or raw_depth.dtype != np.uint16:
                raise DatasetError(f'{sequence.depth.files[index]}: not a 16-bit depth map')
            millimetres = depth_millimetres(raw_depth, sequence.depth_units_per_m)
            yield DEPTH_TOPIC, stamp, build.image(stamp, millimetres, '16UC1')
            count += 1
            continue
        path = sequence.rgb.files[index]
        data = path.read_bytes()
        yield CAMERA_INFO_TOPIC, stamp, build.camera_info(stamp)
        yield IMAGE_TOPIC, stamp, build.compressed(stamp, data)
        count += 2
        if raw:
            yield RAW_IMAGE_TOPIC, stamp, build.image(stamp, _read(path, cv2.IMREAD_COLOR), 'bgr8')
            count += 1
        if sequence.has_pose[index]:
            yield CAMERA_POSE_TOPIC, stamp, build.pose(stamp, sequence.poses[index])
            count += 1
        if progress is not None:
            progress(stamp, count)


def topics(*, raw: bool = False, depth: bool = True) -> list[TopicSpec]:
    """Return the bag's topics."""
    listed = [(CAMERA_INFO_TOPIC, CAMERA_INFO_TYPE), (IMAGE_TOPIC, IMAGE_TYPE)]
    if raw:
        listed.append((RAW_IMAGE_TOPIC, RAW_IMAGE_TYPE))
    listed.append((CAMERA_POSE_TOPIC, POSE_TYPE))
    if depth:
        listed.append((DEPTH_TOPIC, RAW_IMAGE_TYPE))
    return [TopicSpec(name, msgtype, output_qos()) for name, msgtype in listed]


def write_tum_rgbd_bag(
    sequence: TumRgbd,
    path: Path | str,
    *,
    raw: bool = False,
    depth: bool = True,
    single_file: bool = False,
    registry: TypeRegistry | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> TumRgbdBag:
    """Write ``sequence`` as a bag at ``path``; BagError (``path``), DatasetError (image)."""
    started = time.monotonic()
    registry = registry if registry is not None else TypeRegistry()
    messages = tum_rgbd_messages(sequence, registry, raw=raw, depth=depth, progress=progress)
    written = write_bag(
        path, topics(raw=raw, depth=depth), messages, registry=registry, single_file=single_file
    )
    return TumRgbdBag(written, sequence, time.monotonic() - started)


def summary(bag: TumRgbdBag) -> str:
    """Return the one-line summary of a written bag."""
    sequence, written = bag.sequence, bag.written
    counts = sequence.counts()
    span_s = (int(sequence.stamps_ns[-1]) - int(sequence.stamps_ns[0])) / 1e9
    return (
        f'{PROG}: wrote {written.path} ({written.size_bytes / 1e6:.1f} MB): '
        f'{counts["images"]} images over {span_s:.1f} s, '
        f'{written.counts.get(DEPTH_TOPIC, 0)} depth maps, '
        f'{counts["images_with_pose"]} camera poses ({sequence.convention} convention; '
        f'without a pose: {counts["before_truth"]} before the ground truth, '
        f'{counts["after_truth"]} after it, {counts["in_gap"]} in its gaps); '
        f'{counts["images_with_depth"]} images with a depth map within the tolerance; '
        f'{bag.elapsed_s:.1f} s'
    )


def add_dataset_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options that read a TUM-layout sequence (``read_dataset``)."""
    parser.add_argument(
        '--dataset', required=True, type=Path, metavar='DIR',
        help='sequence directory (rgb.txt, depth.txt, groundtruth.txt)',
    )  # fmt: skip
    parser.add_argument(
        '--convention',
        choices=POSE_CONVENTIONS,
        default='camera',
        help="ground-truth rows: 'camera' (TUM: the camera's poses) or 'bonn' (the "
        "motion-capture marker's, converted with the Bonn dataset's T_m); default camera",
    )
    parser.add_argument(
        '--intrinsics',
        choices=tuple(INTRINSICS_PRESETS),
        default=None,
        help="published intrinsics; default 'bonn' with --convention bonn (otherwise give "
        'this or --fx --fy --cx --cy)',
    )
    explicit = parser.add_argument_group(
        'explicit intrinsics',
        'all four together, px; they override a preset, which then only gives its distortion',
    )
    for name in ('fx', 'fy', 'cx', 'cy'):
        explicit.add_argument(f'--{name}', type=float, default=None, metavar='PX')
    parser.add_argument(
        '--tolerance-s',
        type=float,
        metavar='S',
        default=DEFAULT_TOLERANCE_NS / 1e9,
        help='largest stamp difference of a colour image and its depth map, s (default 0.02)',
    )
    parser.add_argument(
        '--max-gap-s',
        type=float,
        metavar='S',
        default=DEFAULT_MAX_GAP_NS / 1e9,
        help='no pose between ground-truth rows further apart, s (default 0.2)',
    )
    parser.add_argument(
        '--depth-units-per-m',
        type=float,
        metavar='UNITS',
        default=DEPTH_UNITS_PER_M,
        help='depth map units per metre (default 5000, as TUM and Bonn)',
    )


def read_dataset(parser: argparse.ArgumentParser, args: argparse.Namespace) -> TumRgbd:
    """Return the sequence the options name; a bad option exits, a bad file: DatasetError."""
    explicit = [getattr(args, name) for name in ('fx', 'fy', 'cx', 'cy')]
    intrinsics: Intrinsics | str
    if any(value is not None for value in explicit):
        if any(value is None for value in explicit):
            parser.error('--fx, --fy, --cx and --cy go together')
        fx, fy, cx, cy = (float(value) for value in explicit)
        base = INTRINSICS_PRESETS[args.intrinsics] if args.intrinsics else None
        intrinsics = Intrinsics(fx, fy, cx, cy, base.distortion if base else ())
    elif args.intrinsics is not None:
        intrinsics = args.intrinsics
    elif args.convention == 'bonn':
        intrinsics = 'bonn'
    else:
        parser.error('give --intrinsics (a preset) or --fx --fy --cx --cy')
    for option, value in (
        ('--tolerance-s', args.tolerance_s),
        ('--max-gap-s', args.max_gap_s),
        ('--depth-units-per-m', args.depth_units_per_m),
    ):
        if not (np.isfinite(value) and value > 0.0):
            parser.error(f'{option} must be a finite number > 0, got {value}')
    return read_tum_rgbd(
        args.dataset,
        convention=args.convention,
        intrinsics=intrinsics,
        tolerance_ns=round(args.tolerance_s * 1e9),
        max_gap_ns=round(args.max_gap_s * 1e9),
        depth_units_per_m=args.depth_units_per_m,
    )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG, description=__doc__, formatter_class=PlainDescriptionHelpFormatter
    )
    add_dataset_arguments(parser)
    parser.add_argument(
        '--output',
        required=True,
        type=Path,
        metavar='PATH',
        help='new bag directory (or .mcap file with --single-file)',
    )
    parser.add_argument('--single-file', action='store_true', help='write one bare .mcap file')
    parser.add_argument(
        '--raw', action='store_true', help='also write the decoded colour images (bgr8)'
    )
    parser.add_argument('--no-depth', action='store_true', help='leave the depth maps out')
    return parser


@console_main(PROG)
def main(argv: list[str] | None = None) -> int:
    """Import a TUM-layout RGB-D sequence and write it as a bag."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    sequence = read_dataset(parser, args)
    check_output(args.output, single_file=args.single_file)
    first = int(sequence.stamps_ns[0])
    reporter = ProgressReporter((int(sequence.stamps_ns[-1]) - first) / 1e9, label=PROG, unit='s')
    bag = write_tum_rgbd_bag(
        sequence,
        args.output,
        raw=args.raw,
        depth=not args.no_depth,
        single_file=args.single_file,
        progress=lambda stamp_ns, items: reporter.update((stamp_ns - first) / 1e9, items=items),
    )
    reporter.update(reporter.total, items=sum(bag.written.counts.values()))
    reporter.finish()
    print(summary(bag))  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
