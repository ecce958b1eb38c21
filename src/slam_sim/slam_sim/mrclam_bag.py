"""mrclam_import: UTIAS MRCLAM robots as rosbag2 mcap bags, with what ground truth exists.

One bag per robot at the data set's times (docs/design/simulation.md). Topics:
  /odom (nav_msgs/Odometry, odom -> base_link); /landmark_observations (base_link)
  /ground_truth/pose (map): the robot's Vicon poses, where the data set has them
  /ground_truth/robots (map -> robotK): the other robots' Vicon poses, <= 10 Hz
  /ground_truth/landmarks (transient-local): static landmarks, then the other robots
  (moveable; position NaN without a Vicon track)"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.arrays import FloatArray, IntArray
from slam_core.cli import PlainTextHelpFormatter, console_main
from slam_core.datasets import data_root
from slam_core.errors import BagError
from slam_core.progress import ProgressReporter
from slam_ros.qos import latched_qos, output_qos
from slam_ros.typesys import TypeRegistry
from slam_sim.core.mrclam import (
    ROBOT_SUBJECTS,
    MrclamRun,
    Sightings,
    parse_mrclam,
    robots_with_odometry,
)
from slam_sim.dataset_bag import (
    LANDMARK_MAP_TYPE,
    OBSERVATIONS_TYPE,
    ODOMETRY_TYPE,
    MessageFactory,
    TopicSpec,
    WrittenBag,
    check_output,
    write_bag,
)
from slam_sim.office_bag import ODOM_POSE_COVARIANCE_DIAGONAL

PROG = 'mrclam_import'
DATASET_DIR = 'mrclam/MRCLAM_Dataset6'
DEFAULT_RANGE_SIGMA_M = 0.079
DEFAULT_BEARING_SIGMA_RAD = 0.011
ROBOT_TRUTH_MIN_PERIOD_NS = 100_000_000  # /ground_truth/robots at most 10 Hz per robot
# Twist variance diagonal (vx, vy, vz, wx, wy, wz) of /odom: nominal, the data give none.
ODOM_TWIST_COVARIANCE_DIAGONAL = (1e-4, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3)
ODOM_TOPIC = '/odom'
OBSERVATIONS_TOPIC = '/landmark_observations'
TRUE_POSE_TOPIC = '/ground_truth/pose'
TRUE_ROBOTS_TOPIC = '/ground_truth/robots'
TRUE_LANDMARKS_TOPIC = '/ground_truth/landmarks'
# At equal stamps messages are written in this order.
TOPICS = (
    TopicSpec(TRUE_LANDMARKS_TOPIC, LANDMARK_MAP_TYPE, latched_qos()),
    TopicSpec(TRUE_POSE_TOPIC, ODOMETRY_TYPE, output_qos()),
    TopicSpec(TRUE_ROBOTS_TOPIC, ODOMETRY_TYPE, output_qos()),
    TopicSpec(ODOM_TOPIC, ODOMETRY_TYPE, output_qos()),
    TopicSpec(OBSERVATIONS_TOPIC, OBSERVATIONS_TYPE, output_qos()),
)
_RANK = {topic.name: rank for rank, topic in enumerate(TOPICS)}


def bag_topics(run: MrclamRun) -> tuple[TopicSpec, ...]:
    """Return the topics a robot's bag holds: the ground-truth tracks only where they exist."""
    absent = set()
    if run.truth is None:
        absent.add(TRUE_POSE_TOPIC)
    if not run.robot_truth:
        absent.add(TRUE_ROBOTS_TOPIC)
    return tuple(topic for topic in TOPICS if topic.name not in absent)


def thin_stamps(stamps_ns: IntArray, min_period_ns: int) -> IntArray:
    """Return indices of increasing ``stamps_ns`` (n,) kept at least ``min_period_ns`` apart."""
    kept: list[int] = []
    next_ns: int | None = None
    for index, stamp in enumerate(np.asarray(stamps_ns).tolist()):
        if next_ns is None or stamp >= next_ns:
            kept.append(index)
            next_ns = stamp + min_period_ns
    return np.array(kept, dtype=np.int64)


def observation_frames(sightings: Sightings) -> tuple[IntArray, IntArray]:
    """Return the distinct sighting stamps (F,) and row bounds (F + 1,)."""
    stamps, starts = np.unique(sightings.stamps_ns, return_index=True)
    return stamps, np.append(starts, len(sightings)).astype(np.int64)


def robot_truth_rows(run: MrclamRun) -> dict[int, IntArray]:
    """Return, per other robot with a Vicon track, the rows written to /ground_truth/robots."""
    return {
        k: thin_stamps(run.robot_truth[k].stamps_ns, ROBOT_TRUTH_MIN_PERIOD_NS)
        for k in run.other_robots
        if k in run.robot_truth
    }


def landmark_table(run: MrclamRun) -> tuple[IntArray, FloatArray, FloatArray, np.ndarray]:
    """Return the truth map: subjects (L,), positions (L, 2) m, covariances, moveable."""
    others = run.other_robots
    subjects = np.concatenate([run.landmarks.subjects, np.array(others, dtype=np.int64)])
    first = [
        run.robot_truth[k].poses[0, :2] if k in run.robot_truth else np.full(2, np.nan)
        for k in others
    ]
    positions = np.concatenate([run.landmarks.positions, np.array(first).reshape(-1, 2)])
    covariances = np.zeros((len(subjects), 2, 2))
    static = len(run.landmarks.subjects)
    covariances[:static, 0, 0] = run.landmarks.std_m[:, 0] ** 2
    covariances[:static, 1, 1] = run.landmarks.std_m[:, 1] ** 2
    for row, k in enumerate(others, start=static):
        if k not in run.robot_truth:
            covariances[row] = np.nan
    moveable = np.arange(len(subjects)) >= static
    return subjects, positions, covariances, moveable


def _schedule(run: MrclamRun, frame_stamps: IntArray) -> np.ndarray:
    """Return (stamp ns, topic rank, item, robot subject) rows (n, 4) in writing order."""
    own_truth = [] if run.truth is None else [(run.truth.stamps_ns, _RANK[TRUE_POSE_TOPIC], 0)]
    parts = [
        own_truth,
        [(run.odometry.stamps_ns, _RANK[ODOM_TOPIC], 0)],
        [(frame_stamps, _RANK[OBSERVATIONS_TOPIC], 0)],
        [
            (run.robot_truth[k].stamps_ns[rows], _RANK[TRUE_ROBOTS_TOPIC], k)
            for k, rows in robot_truth_rows(run).items()
        ],
    ]
    blocks = [
        np.column_stack(
            [stamps, np.full(len(stamps), rank), np.arange(len(stamps)), np.full(len(stamps), k)]
        ).astype(np.int64)
        for part in parts
        for stamps, rank, k in part
    ]
    rows = np.concatenate(blocks)
    start = int(rows[:, 0].min())
    rows = np.concatenate([[[start, _RANK[TRUE_LANDMARKS_TOPIC], 0, 0]], rows])
    return rows[np.lexsort((rows[:, 3], rows[:, 1], rows[:, 0]))]


def mrclam_messages(
    run: MrclamRun, registry: TypeRegistry, *, observation_sigmas: tuple[float, float]
) -> Iterator[tuple[str, int, Any]]:
    """Yield (topic, bag stamp ns, message) of a robot's run in stamp order; sigmas m, rad."""
    build = MessageFactory(registry, [topic.msgtype for topic in TOPICS])
    truth = run.truth
    sightings = run.sightings
    frame_stamps, bounds = observation_frames(sightings)
    range_bearing = np.column_stack([sightings.range_m, sightings.bearing_rad])
    observation_cov = np.diag(np.square(observation_sigmas))
    thinned = robot_truth_rows(run)
    zeros = np.zeros(36)
    odom_cov = (
        np.diag(ODOM_POSE_COVARIANCE_DIAGONAL).reshape(36),
        np.diag(ODOM_TWIST_COVARIANCE_DIAGONAL).reshape(36),
    )
    no_twist = np.zeros(2)
    for stamp, rank, item, subject in _schedule(run, frame_stamps).tolist():
        topic = TOPICS[rank].name
        if topic == TRUE_LANDMARKS_TOPIC:
            subjects, positions, covariances, moveable = landmark_table(run)
            counts = [int(np.count_nonzero(sightings.subjects == s)) for s in subjects]
            message = build.landmark_map(
                stamp, subjects, positions, covariances, moveable, np.array(counts)
            )
        elif topic == TRUE_POSE_TOPIC and truth is not None:
            pose = truth.poses[item]
            message = build.odometry(stamp, ('map', 'base_link'), pose, no_twist, (zeros, zeros))
        elif topic == TRUE_ROBOTS_TOPIC:
            pose = run.robot_truth[subject].poses[thinned[subject][item]]
            frames = ('map', f'robot{subject}')
            message = build.odometry(stamp, frames, pose, no_twist, (zeros, zeros))
        elif topic == ODOM_TOPIC:
            odometry = run.odometry
            message = build.odometry(
                stamp, ('odom', 'base_link'), odometry.poses[item], odometry.twists[item], odom_cov
            )
        else:
            rows = slice(int(bounds[item]), int(bounds[item + 1]))
            covariances = np.broadcast_to(observation_cov, (rows.stop - rows.start, 2, 2))
            message = build.observations(
                stamp, sightings.subjects[rows], range_bearing[rows], covariances
            )
        yield topic, stamp, message


def write_mrclam_bag(
    run: MrclamRun,
    path: Path | str,
    *,
    range_sigma_m: float = DEFAULT_RANGE_SIGMA_M,
    bearing_sigma_rad: float = DEFAULT_BEARING_SIGMA_RAD,
    single_file: bool = False,
    registry: TypeRegistry | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> WrittenBag:
    """Write one robot's run as an mcap bag at ``path``; BagError, ValueError (sigma)."""
    for name, sigma in (
        ('range_sigma_m', range_sigma_m),
        ('bearing_sigma_rad', bearing_sigma_rad),
    ):
        if not (np.isfinite(sigma) and sigma > 0.0):
            raise ValueError(f'{name} must be a finite number > 0, got {sigma}')
    registry = registry if registry is not None else TypeRegistry()
    messages = mrclam_messages(
        run, registry, observation_sigmas=(range_sigma_m, bearing_sigma_rad)
    )
    return write_bag(
        path,
        bag_topics(run),
        messages,
        registry=registry,
        single_file=single_file,
        progress=progress,
    )


def run_span_ns(run: MrclamRun) -> tuple[int, int]:
    """Return the first and last stamp (int ns) a robot's bag holds."""
    stamps = [run.odometry.stamps_ns, run.sightings.stamps_ns]
    stamps += [] if run.truth is None else [run.truth.stamps_ns]
    stamps += [t.stamps_ns for t in run.robot_truth.values()]
    return min(int(s[0]) for s in stamps if len(s)), max(int(s[-1]) for s in stamps if len(s))


def summary(run: MrclamRun, written: WrittenBag) -> str:
    """Return the one-line summary of a written robot bag."""
    first, last = run_span_ns(run)
    seen = {k: int(np.count_nonzero(run.sightings.subjects == k)) for k in run.other_robots}
    dropped = ', '.join(f'{reason} {count}' for reason, count in run.dropped_counts.items())
    return (
        f'{PROG}: wrote {written.path} ({written.size_bytes / 1e6:.2f} MB): robot {run.robot}, '
        f'{(last - first) / 1e9:.1f} s, {written.counts[ODOM_TOPIC]} odometry '
        f'({run.misplaced_odometry_rows} rows out of time order sorted, '
        f'{run.duplicate_odometry_stamps} repeated stamps dropped), '
        f'{written.counts[OBSERVATIONS_TOPIC]} observation messages with '
        f'{len(run.sightings)} sightings (dropped: {dropped}), sightings of robots {seen}; '
        f'Vicon tracks: {"own" if run.truth is not None else "no own"}, other robots '
        f'{sorted(run.robot_truth) or "none"}'
    )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG, description=__doc__, formatter_class=PlainTextHelpFormatter
    )
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument('--robot', type=int, choices=ROBOT_SUBJECTS, help='robot to import')
    which.add_argument(
        '--all', action='store_true', help='import every robot into the directory --output'
    )
    parser.add_argument(
        '--dataset',
        type=Path,
        default=None,
        help=f'MRCLAM data set directory (default: <datasets>/{DATASET_DIR})',
    )
    parser.add_argument(
        '--output',
        required=True,
        type=Path,
        help='bag directory (or .mcap file with --single-file) to create; with --all a new '
        "directory for the robots' bags",
    )
    parser.add_argument(
        '--range-sigma',
        type=float,
        default=DEFAULT_RANGE_SIGMA_M,
        help='standard deviation of a range measurement, m',
    )
    parser.add_argument(
        '--bearing-sigma',
        type=float,
        default=DEFAULT_BEARING_SIGMA_RAD,
        help='standard deviation of a bearing measurement, rad',
    )
    parser.add_argument(
        '--window-s',
        '--max-duration-s',
        dest='window_s',
        type=float,
        default=None,
        metavar='S',
        help='keep only the first S seconds from the first odometry stamp (default: all)',
    )
    parser.add_argument(
        '--single-file',
        action='store_true',
        help='write one bare .mcap file per robot instead of a bag directory',
    )
    return parser


def _validate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    for option, value in (
        ('--range-sigma', args.range_sigma),
        ('--bearing-sigma', args.bearing_sigma),
    ):
        if not (np.isfinite(value) and value > 0.0):
            parser.error(f'{option} must be a finite number > 0, got {value}')
    duration = args.window_s
    if duration is not None and not (np.isfinite(duration) and duration > 0.0):
        parser.error(f'--window-s must be a finite number > 0, got {duration}')


def load_run(dataset: Path, robot: int, window_s: float | None = None) -> MrclamRun:
    """Return robot ``robot`` of ``dataset`` cut to ``window_s`` s; warn of unordered rows."""
    run = parse_mrclam(dataset, robot)
    if run.misplaced_odometry_rows:
        print(  # noqa: T201
            f'{PROG}: warning: {dataset / f"Robot{robot}_Odometry.dat"}: '
            f'{run.misplaced_odometry_rows} rows out of time order, sorted by time',
            file=sys.stderr,
        )
    return run if window_s is None else run.first_seconds(window_s)


def _write(run: MrclamRun, path: Path, args: argparse.Namespace) -> WrittenBag:
    first, last = run_span_ns(run)
    reporter = ProgressReporter((last - first) / 1e9, label=f'{PROG} robot {run.robot}', unit='s')
    written = write_mrclam_bag(
        run,
        path,
        range_sigma_m=args.range_sigma,
        bearing_sigma_rad=args.bearing_sigma,
        single_file=args.single_file,
        progress=lambda bag_ns, items: reporter.update((bag_ns - first) / 1e9, items=items),
    )
    reporter.update((last - first) / 1e9, items=sum(written.counts.values()))
    reporter.finish()
    return written


def _write_all(runs: list[MrclamRun], target: Path, args: argparse.Namespace) -> list[str]:
    """Write every robot into a staging directory, then move it to ``target``."""
    staging = target.parent / f'.{target.name}.writing-{os.getpid()}'
    lines = []
    try:
        staging.mkdir()
        for run in runs:
            name = f'robot{run.robot}' + ('.mcap' if args.single_file else '')
            written = _write(run, staging / name, args)
            lines.append(summary(run, replace(written, path=target / name)))
        staging.rename(target)
    except OSError as err:
        raise BagError(f'output {str(target)!r} cannot be written: {err}') from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return lines


@console_main(PROG)
def main(argv: list[str] | None = None) -> int:
    """Import one or every MRCLAM robot and write bags."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    _validate(parser, args)
    dataset = args.dataset if args.dataset is not None else data_root() / DATASET_DIR
    if args.all:
        target = args.output.expanduser().absolute()
        if target.exists():
            raise BagError(f'output {str(target)!r} exists already; remove it or choose another')
        if not target.parent.is_dir():
            raise BagError(f'output {str(target)!r}: directory {str(target.parent)!r} is missing')
        robots = robots_with_odometry(dataset)
        skipped = [k for k in ROBOT_SUBJECTS if k not in robots]
        if skipped:
            print(  # noqa: T201
                f'{PROG}: note: {dataset}: no odometry file for robots {skipped}; skipped',
                file=sys.stderr,
            )
        runs = [load_run(dataset, robot, args.window_s) for robot in robots]
        lines = _write_all(runs, target, args)
    else:
        check_output(args.output, single_file=args.single_file)
        run = load_run(dataset, args.robot, args.window_s)
        lines = [summary(run, _write(run, args.output, args))]
    for line in lines:
        print(line)  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
