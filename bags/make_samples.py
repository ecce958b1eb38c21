"""Regenerate the sample bags in bags/ from the shared datasets.

    python bags/make_samples.py            # datasets from $SLAM_DATA_DIR or ../shared/data

ubiquity_aruco/: the Ubiquity Robotics ``aruco_images.bag`` (ROS 1, BSD-3) converted to an
mcap rosbag2 bag, with its topics renamed to the suite's defaults:
  /raspicam_node/image/compressed -> /camera/image_raw/compressed
  /raspicam_node/camera_info      -> /camera/camera_info
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rosbags.rosbag2 import StoragePlugin, Writer

from slam_core.datasets import data_root
from slam_ros.bag.source import BagSource
from slam_ros.qos import output_qos, recorded_from_profile
from slam_ros.typesys import TypeRegistry

UBIQUITY_RENAMES = {
    '/raspicam_node/image/compressed': '/camera/image_raw/compressed',
    '/raspicam_node/camera_info': '/camera/camera_info',
}


def convert(source_path: Path, target: Path, renames: dict[str, str]) -> int:
    """Convert ``source_path`` (any bag) to an mcap bag at ``target``; return messages written."""
    registry = TypeRegistry()
    written = 0
    with (
        BagSource(source_path) as source,
        Writer(target, version=9, storage_plugin=StoragePlugin.MCAP) as writer,
    ):
        connections = {}
        for name, topic in sorted(source.topics().items()):
            msgdef, rihs01 = registry.msgdef_and_hash(topic.msgtype)
            connections[name] = writer.add_connection(
                renames.get(name, name),
                topic.msgtype,
                msgdef=msgdef,
                rihs01=rihs01,
                offered_qos_profiles=[recorded_from_profile(output_qos())],
            )
        for message in source.messages(validate=True):
            writer.write(connections[message.topic], message.timestamp_ns, message.data)
            written += 1
    return written


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data', type=Path, default=data_root(), help='datasets directory')
    parser.add_argument('--out', type=Path, default=Path(__file__).resolve().parent)
    args = parser.parse_args()
    source = args.data / 'fiducials_ubiquity' / 'aruco_images.bag'
    if not source.exists():
        print(f'make_samples: error: {source} not found (set SLAM_DATA_DIR)', file=sys.stderr)
        return 2
    target = args.out / 'ubiquity_aruco'
    if target.exists():
        print(f'make_samples: {target} exists; delete it to regenerate', file=sys.stderr)
        return 0
    count = convert(source, target, UBIQUITY_RENAMES)
    print(f'wrote {count} messages to {target}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
