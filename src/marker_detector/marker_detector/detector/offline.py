"""marker_detect_bag: run the marker detector over a recorded camera bag, offline.

Writes a new bag: every other topic copied, plus /fiducials and /landmark_observations at the
images' receive stamps, as the node would publish them with the same YAML (--params); the
images too with --keep-images; nothing at --output unless complete.

    marker_detect_bag bags/office_camera.mcap --output out/office_detected
    em_sam_evaluate out/office_detected
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.serialization import serialize_message

from marker_detector.common.conversions import (
    camera_info_fields,
    fill_observations,
    transform_matrix,
)
from marker_detector.core.frame_types import InputError
from marker_detector.detector.conversions import fill_fiducials, image_from_message
from marker_detector.detector.processor import MarkerProcessor
from marker_detector.detector.settings import (
    PARAMETERS,
    apply_overrides,
    detector_config,
    extrinsics_config,
    search_plan,
)
from slam_core.cli import console_main
from slam_core.errors import BagError, ParameterError
from slam_core.images import ImageError
from slam_core.progress import ProgressReporter
from slam_core.stamps import stamp_to_ns
from slam_interfaces.msg import (
    FiducialArray,
    FiducialDetection,
    LandmarkObservation,
    LandmarkObservationArray,
)
from slam_ros.bag.recording import AtomicBagWriter
from slam_ros.bag.source import BagSource
from slam_ros.qos import output_qos, recorded_from_profile
from slam_ros.typesys import TypeRegistry

PROG = 'marker_detect_bag'
IMAGE_TOPICS = ('/camera/image_raw/compressed', '/camera/image_raw')
CAMERA_INFO_TOPIC = '/camera/camera_info'
TF_STATIC_TOPIC = '/tf_static'
FIDUCIALS_TOPIC = '/fiducials'
OBSERVATIONS_TOPIC = '/landmark_observations'
FIDUCIALS_TYPE = 'slam_interfaces/msg/FiducialArray'
OBSERVATIONS_TYPE = 'slam_interfaces/msg/LandmarkObservationArray'


@dataclass
class DetectStats:
    """What a run of the offline detector did."""

    images: int = 0
    images_with_markers: int = 0
    detections: int = 0
    dropped: Counter[str] = field(default_factory=Counter)
    rejections: Counter[str] = field(default_factory=Counter)
    camera_info_errors: Counter[str] = field(default_factory=Counter)
    tf_static_errors: Counter[str] = field(default_factory=Counter)
    output: Path | None = None

    def summary(self) -> str:
        """One paragraph for the terminal."""
        lines = [
            f'{PROG}: {self.images} images, {self.images_with_markers} with markers, '
            f'{self.detections} markers accepted; wrote {self.output}'
        ]
        for reason, count in self.dropped.most_common():
            lines.append(f'  dropped {count} images: {reason}')
        for reason, count in self.camera_info_errors.most_common():
            lines.append(f'  {count} camera_info messages unusable: {reason}')
        for reason, count in self.tf_static_errors.most_common():
            lines.append(f'  {count} /tf_static transforms unusable: {reason}')
        for gate, count in self.rejections.most_common():
            lines.append(f'  rejected {count} markers: {gate}')
        return '\n'.join(lines)


def detect_bag(
    source_path: Path,
    output: Path,
    values: dict[str, Any],
    *,
    image_topic: str | None = None,
    keep_images: bool = False,
    progress: bool = True,
) -> DetectStats:
    """Run the detector over ``source_path``, write ``output``, return the statistics;
    BagError for an unusable bag or no usable image, ParameterError for a bad setting."""
    try:
        processor = MarkerProcessor(
            detector_config(values), extrinsics_config(values), search_plan(values)
        )
    except ValueError as err:
        raise ParameterError(str(err)) from None
    registry = TypeRegistry()
    stats = DetectStats()
    with BagSource(source_path) as source:
        topics = source.topics()
        if image_topic is None:
            image_topic = next((t for t in IMAGE_TOPICS if t in topics), None)
        if image_topic is None or image_topic not in topics:
            raise BagError(
                f'bag {str(source_path)!r} has no image topic '
                f'({image_topic or " or ".join(IMAGE_TOPICS)}); '
                f'topics: {", ".join(sorted(topics))}'
            )
        if CAMERA_INFO_TOPIC not in topics:
            raise BagError(f'bag {str(source_path)!r} has no {CAMERA_INFO_TOPIC} topic')
        for name in (image_topic, CAMERA_INFO_TOPIC, TF_STATIC_TOPIC):
            if name in topics:
                registry.ensure(topics[name].msgtype)
        store = registry.typestore
        writer = AtomicBagWriter(output)
        try:
            copied = [t for t in topics if keep_images or t != image_topic]
            for name in copied:
                if name in (FIDUCIALS_TOPIC, OBSERVATIONS_TOPIC):
                    continue  # replaced by this run's detections
                summary = topics[name]
                msgdef, rihs01 = registry.msgdef_and_hash(summary.msgtype)
                writer.add_topic(
                    name,
                    summary.msgtype,
                    msgdef=msgdef,
                    rihs01=rihs01,
                    offered_qos=list(summary.offered_qos),
                )
            for name, msgtype in (
                (FIDUCIALS_TOPIC, FIDUCIALS_TYPE),
                (OBSERVATIONS_TOPIC, OBSERVATIONS_TYPE),
            ):
                msgdef, rihs01 = registry.msgdef_and_hash(msgtype)
                writer.add_topic(
                    name,
                    msgtype,
                    msgdef=msgdef,
                    rihs01=rihs01,
                    offered_qos=[recorded_from_profile(output_qos())],
                )
            reporter = (
                ProgressReporter(source.duration_ns / 1e9, label=PROG, unit='s')
                if progress
                else None
            )
            for message in source.messages():
                if writer.has_topic(message.topic) and message.topic not in (
                    FIDUCIALS_TOPIC,
                    OBSERVATIONS_TOPIC,
                ):
                    writer.write(message.topic, message.timestamp_ns, message.data)
                if message.topic == CAMERA_INFO_TOPIC:
                    info = store.deserialize_cdr(message.data, message.msgtype)
                    try:
                        processor.set_camera_info(**camera_info_fields(info))
                    except InputError as err:
                        stats.camera_info_errors[str(err)] += 1
                elif message.topic == TF_STATIC_TOPIC:
                    tf_message: Any = store.deserialize_cdr(message.data, message.msgtype)
                    for transform in tf_message.transforms:
                        try:
                            processor.transforms.add(
                                transform.header.frame_id,
                                transform.child_frame_id,
                                transform_matrix(transform.transform),
                            )
                        except InputError as err:  # as the node: counted, the run goes on
                            stats.tf_static_errors[str(err)] += 1
                elif message.topic == image_topic:
                    _detect_one(processor, store, message, writer, stats)
                    if reporter is not None:
                        reporter.update(
                            (message.timestamp_ns - source.start_ns) / 1e9, items=stats.images
                        )
            if reporter is not None:
                reporter.finish()
            _check_something_detected(stats, image_topic)
        except BaseException:
            writer.abort()
            raise
        stats.output = writer.close()
    return stats


def _check_something_detected(stats: DetectStats, image_topic: str) -> None:
    """Raise BagError when no image could be searched (nothing worth writing)."""
    dropped = sum(stats.dropped.values())
    if stats.images and dropped < stats.images:
        return
    if not stats.images:
        raise BagError(f'{image_topic} has no messages: nothing to detect in; nothing written')
    reason, count = stats.dropped.most_common(1)[0]
    others = f' ({dropped - count} for other reasons)' if dropped > count else ''
    raise BagError(
        f'all {stats.images} images on {image_topic} were dropped, {count} of them because '
        f'{reason}{others}; nothing written'
    )


def _detect_one(
    processor: MarkerProcessor,
    store: Any,
    message: Any,
    writer: AtomicBagWriter,
    stats: DetectStats,
) -> None:
    stats.images += 1
    decoded: Any = store.deserialize_cdr(message.data, message.msgtype)
    try:
        image = image_from_message(decoded)
        output = processor.process(
            stamp_to_ns(decoded.header.stamp), str(decoded.header.frame_id), image
        )
    except (ImageError, InputError) as err:
        reason = str(err).split(': ', 1)[-1] if str(err).startswith('image at') else str(err)
        stats.dropped[reason] += 1
        return
    stats.detections += len(output.detections)
    for rejection in output.rejections:
        stats.rejections[rejection.gate] += 1
    fiducials = fill_fiducials(output, FiducialArray(), FiducialDetection)
    writer.write(FIDUCIALS_TOPIC, message.timestamp_ns, serialize_message(fiducials))
    stats.images_with_markers += bool(output.observations)
    # empty too, as the node publishes them (odometry_ingest reads how far the detector got)
    observations = fill_observations(output, LandmarkObservationArray(), LandmarkObservation)
    writer.write(OBSERVATIONS_TOPIC, message.timestamp_ns, serialize_message(observations))


@console_main(PROG)
def main(argv: list[str] | None = None) -> int:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument('bag', type=Path, help='input bag (mcap or sqlite3 rosbag2, or ROS 1)')
    parser.add_argument('--output', type=Path, required=True, help='output bag directory (new)')
    parser.add_argument(
        '--params',
        type=Path,
        action='append',
        default=[],
        help='a node YAML parameter file; repeatable, later files override earlier ones',
    )
    parser.add_argument(
        '--image-topic', help=f'image topic (default: {" or ".join(IMAGE_TOPICS)})'
    )
    parser.add_argument(
        '--set',
        action='append',
        default=[],
        metavar='NAME=VALUE',
        help='override one parameter (YAML value, e.g. marker_size_m=0.25); repeatable',
    )
    parser.add_argument('--keep-images', action='store_true', help='copy the images too')
    args = parser.parse_args(argv)
    values: dict[str, Any] = PARAMETERS.defaults()
    for path in args.params:
        values = PARAMETERS.read_yaml(path, values)
    values = PARAMETERS.validate(apply_overrides(values, args.set))
    stats = detect_bag(
        args.bag, args.output, values, image_topic=args.image_topic, keep_images=args.keep_images
    )
    print(stats.summary())  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
