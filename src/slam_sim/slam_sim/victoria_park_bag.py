"""victoria_park_import: the Victoria Park data set (GTSAM text format) as a rosbag2 mcap bag.

Pose i is stamped --start-ns + i * --period-s (docs/design/simulation.md). Topics:
  /odometry_increments (slam_interfaces/OdometryIncrement, base_link): EM-SAM eq. 2,
    one per ODOMETRY line
  /landmark_observations (slam_interfaces/LandmarkObservationArray, base_link): range and
    bearing per pose with sightings, GTSAM load2D's sigmas"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.cli import PlainTextHelpFormatter, console_main
from slam_core.datasets import data_root
from slam_core.progress import ProgressReporter
from slam_ros.qos import output_qos
from slam_ros.typesys import TypeRegistry
from slam_sim.core.victoria_park import (
    VictoriaPark,
    chain_poses,
    differential_drive_increments,
    parse_victoria_park,
    sighting_covariances,
)
from slam_sim.dataset_bag import (
    INCREMENT_TYPE,
    OBSERVATIONS_TYPE,
    MessageFactory,
    TopicSpec,
    WrittenBag,
    check_output,
    write_bag,
)
from slam_sim.office_bag import DEFAULT_START_NS

PROG = 'victoria_park_import'
DATASET_FILE = 'victoria_park/victoria_park.txt'
DEFAULT_PERIOD_S = 0.1
INCREMENTS_TOPIC = '/odometry_increments'
OBSERVATIONS_TOPIC = '/landmark_observations'
QUEUE_DEPTH = 1000
TOPICS = (
    TopicSpec(INCREMENTS_TOPIC, INCREMENT_TYPE, output_qos(depth=QUEUE_DEPTH)),
    TopicSpec(OBSERVATIONS_TOPIC, OBSERVATIONS_TYPE, output_qos(depth=QUEUE_DEPTH)),
)


def pose_stamps_ns(num_poses: int, *, start_ns: int, period_ns: int) -> np.ndarray:
    """Return the nominal stamps (N,) int ns of poses 0..N-1."""
    if period_ns <= 0:
        raise ValueError(f'the pose period must be > 0 ns, got {period_ns}')
    return start_ns + np.arange(num_poses, dtype=np.int64) * period_ns


def victoria_park_messages(
    data: VictoriaPark, registry: TypeRegistry, *, start_ns: int, period_ns: int
) -> Iterator[tuple[str, int, Any]]:
    """Yield (topic, bag stamp int ns, rosbags message) of the data set, in stamp order."""
    build = MessageFactory(registry, [INCREMENT_TYPE, OBSERVATIONS_TYPE])
    stamps = pose_stamps_ns(data.num_poses, start_ns=start_ns, period_ns=period_ns).tolist()
    u, u_cov = differential_drive_increments(data.odometry_between, data.odometry_cov)
    odom_poses = chain_poses(data.odometry_between)
    edge_to_pose = np.full(data.num_poses, -1, dtype=np.int64)
    edge_to_pose[data.odometry_to] = np.arange(len(data.odometry_to))
    order = np.argsort(data.obs_pose, kind='stable')
    seen_poses, starts = np.unique(data.obs_pose[order], return_index=True)
    stops = [*starts[1:].tolist(), len(order)]
    rows_of_pose = {
        pose: order[start:stop]
        for pose, start, stop in zip(seen_poses.tolist(), starts.tolist(), stops, strict=True)
    }
    range_bearing = np.column_stack([data.obs_range, data.obs_bearing])
    obs_cov = sighting_covariances(data)
    for pose in range(data.num_poses):
        edge = int(edge_to_pose[pose])
        if edge >= 0:
            pose_from = int(data.odometry_from[edge])
            message = build.increment(
                (stamps[pose_from], stamps[pose]),
                u[edge],
                u_cov[edge],
                (odom_poses[pose_from], odom_poses[pose]),
            )
            yield INCREMENTS_TOPIC, stamps[pose], message
        rows = rows_of_pose.get(pose)
        if rows is not None:
            message = build.observations(
                stamps[pose], data.obs_landmark[rows], range_bearing[rows], obs_cov[rows]
            )
            yield OBSERVATIONS_TOPIC, stamps[pose], message


def write_victoria_park_bag(
    data: VictoriaPark,
    path: Path | str,
    *,
    start_ns: int = DEFAULT_START_NS,
    period_s: float = DEFAULT_PERIOD_S,
    single_file: bool = False,
    registry: TypeRegistry | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> WrittenBag:
    """Write ``data`` as an mcap bag at ``path``; BagError, ValueError (``period_s``)."""
    period_ns = round(period_s * 1e9) if np.isfinite(period_s) else 0
    if period_ns <= 0:
        raise ValueError(f'period_s must be >= 1 ns, got {period_s}')
    registry = registry if registry is not None else TypeRegistry()
    messages = victoria_park_messages(data, registry, start_ns=start_ns, period_ns=period_ns)
    return write_bag(
        path, TOPICS, messages, registry=registry, single_file=single_file, progress=progress
    )


def summary(data: VictoriaPark, written: WrittenBag, period_s: float) -> str:
    """Return the one-line summary of a written Victoria Park bag."""
    return (
        f'{PROG}: wrote {written.path} ({written.size_bytes / 1e6:.2f} MB): '
        f'{data.num_poses} poses at a nominal {period_s:g} s, '
        f'{written.counts[INCREMENTS_TOPIC]} odometry increments, '
        f'{len(data.obs_pose)} sightings of {len(data.landmark_ids)} landmarks in '
        f'{written.counts[OBSERVATIONS_TOPIC]} observation messages'
    )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG, description=__doc__, formatter_class=PlainTextHelpFormatter
    )
    parser.add_argument(
        '--input',
        type=Path,
        default=None,
        help=f'GTSAM 2D text file (default: <datasets>/{DATASET_FILE})',
    )
    parser.add_argument(
        '--output',
        required=True,
        type=Path,
        help='bag directory to create (or .mcap file with --single-file)',
    )
    parser.add_argument(
        '--period-s',
        type=float,
        default=DEFAULT_PERIOD_S,
        help='nominal time between consecutive poses, s (the file has no time)',
    )
    parser.add_argument(
        '--start-ns',
        type=int,
        default=DEFAULT_START_NS,
        help='bag time of pose 0, int ns since the epoch',
    )
    parser.add_argument(
        '--single-file',
        action='store_true',
        help='write one bare .mcap file instead of a bag directory',
    )
    return parser


@console_main(PROG)
def main(argv: list[str] | None = None) -> int:
    """Import the Victoria Park file and write it as a bag."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if not (np.isfinite(args.period_s) and round(args.period_s * 1e9) > 0):
        parser.error(f'--period-s must be a positive number of seconds, got {args.period_s}')
    check_output(args.output, single_file=args.single_file)
    source = args.input if args.input is not None else data_root() / DATASET_FILE
    data = parse_victoria_park(source)
    total_s = data.num_poses * args.period_s
    reporter = ProgressReporter(total_s, label=PROG, unit='s')
    written = write_victoria_park_bag(
        data,
        args.output,
        start_ns=args.start_ns,
        period_s=args.period_s,
        single_file=args.single_file,
        progress=lambda bag_ns, items: reporter.update(
            (bag_ns - args.start_ns) / 1e9, items=items
        ),
    )
    reporter.update(total_s, items=sum(written.counts.values()))
    reporter.finish()
    print(summary(data, written, args.period_s))  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
