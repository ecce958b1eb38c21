"""office_sim: simulate the EM-SAM office experiment and write it as a rosbag2 mcap bag.

Topics (stamps --start-ns + run time; reliable; docs/design/simulation.md):
  /odom (nav_msgs/Odometry, odom -> base_link, at --odom-hz): noisy wheel odometry
  /landmark_observations (slam_interfaces/LandmarkObservationArray, base_link): per frame
  /ground_truth/pose (nav_msgs/Odometry, map -> base_link): true pose and velocity
  /ground_truth/landmarks (slam_interfaces/LandmarkMap, transient-local): at start and move"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.cli import PlainTextHelpFormatter, console_main
from slam_core.progress import ProgressReporter
from slam_ros.qos import latched_qos, output_qos
from slam_ros.typesys import TypeRegistry
from slam_sim.core.office import OfficeConfig, OfficeRun, Variant, simulate_office
from slam_sim.dataset_bag import (
    LANDMARK_MAP_TYPE,
    OBSERVATIONS_TYPE,
    ODOMETRY_TYPE,
    MessageFactory,
    TopicSpec,
    WrittenBag,
    write_bag,
)

DEFAULT_START_NS = 1_700_000_000 * 10**9
ODOM_TOPIC = '/odom'
OBSERVATIONS_TOPIC = '/landmark_observations'
TRUE_POSE_TOPIC = '/ground_truth/pose'
TRUE_LANDMARKS_TOPIC = '/ground_truth/landmarks'
# (topic, type, latched); at equal stamps messages are written in this order.
TOPICS = (
    (TRUE_LANDMARKS_TOPIC, LANDMARK_MAP_TYPE, True),
    (TRUE_POSE_TOPIC, ODOMETRY_TYPE, False),
    (ODOM_TOPIC, ODOMETRY_TYPE, False),
    (OBSERVATIONS_TOPIC, OBSERVATIONS_TYPE, False),
)
# Pose covariance of /odom, diagonal of (x, y, z, roll, pitch, yaw): diff_drive_controller's
# usual configuration; wheel odometry does not estimate its own drift.
ODOM_POSE_COVARIANCE_DIAGONAL = (1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-2)
_UNUSED_TWIST_VARIANCE = 1e-3


def odom_twist_covariance_diagonal(config: OfficeConfig) -> tuple[float, ...]:
    """Return the /odom twist variance diagonal (vx, vy, vz, wx, wy, wz) at full speed."""
    noise, motion = config.odometry_noise, config.motion
    v_var = noise.distance_sigma_per_sqrt_m**2 * motion.max_speed_mps * config.odom_rate_hz
    w_var = (
        noise.rotation_sigma_per_sqrt_rad**2 * motion.max_turn_rate_radps
        + noise.rotation_sigma_per_sqrt_m**2 * motion.max_speed_mps
    ) * config.odom_rate_hz
    unused = _UNUSED_TWIST_VARIANCE
    return (v_var, unused, unused, unused, unused, w_var)


def _observation_counts(run: OfficeRun, after: bool) -> dict[int, int]:
    """Non-outlier observations per landmark id before (or from) the move time."""
    observations = run.observations
    in_interval = run.landmarks.after_move(observations.stamps_ns) == after
    ids, counts = np.unique(
        observations.landmark_ids[in_interval & ~observations.is_outlier], return_counts=True
    )
    return dict(zip(ids.tolist(), counts.tolist(), strict=True))


def _schedule(run: OfficeRun) -> tuple[list[tuple[int, int, int]], list[int]]:
    """Return every message as (run stamp ns, TOPICS index, item index), sorted, and bounds."""
    rank = {topic: index for index, (topic, _, _) in enumerate(TOPICS)}
    schedule = [(0, rank[TRUE_LANDMARKS_TOPIC], 0)]
    if run.landmarks.move_time_ns is not None:
        schedule.append((run.landmarks.move_time_ns, rank[TRUE_LANDMARKS_TOPIC], 1))
    for index, stamp in enumerate(run.odometry.stamps_ns.tolist()):
        schedule.append((stamp, rank[TRUE_POSE_TOPIC], index))
        schedule.append((stamp, rank[ODOM_TOPIC], index))
    frame_stamps, frame_starts = np.unique(run.observations.stamps_ns, return_index=True)
    for index, stamp in enumerate(frame_stamps.tolist()):
        schedule.append((stamp, rank[OBSERVATIONS_TOPIC], index))
    return sorted(schedule), [*frame_starts.tolist(), len(run.observations)]


def office_messages(
    run: OfficeRun, registry: TypeRegistry, *, start_ns: int
) -> Iterator[tuple[str, int, Any]]:
    """Yield (topic, bag stamp int ns, rosbags message) of the whole run, in stamp order."""
    build = MessageFactory(registry, {msgtype for _, msgtype, _ in TOPICS})
    schedule, frame_bounds = _schedule(run)
    odometry = run.odometry
    true_poses = run.truth.poses_at(odometry.stamps_ns)
    true_twists = run.truth.twists_at(odometry.stamps_ns)
    zeros = np.zeros(36)
    odom_cov = (
        np.diag(ODOM_POSE_COVARIANCE_DIAGONAL).reshape(36),
        np.diag(odom_twist_covariance_diagonal(run.config)).reshape(36),
    )
    truth = run.landmarks
    for stamp, topic_rank, index in schedule:
        topic, bag_ns = TOPICS[topic_rank][0], start_ns + stamp
        if topic == TRUE_LANDMARKS_TOPIC:
            after = bool(index)
            counts = _observation_counts(run, after)
            message = build.landmark_map(
                bag_ns,
                truth.ids,
                truth.positions_after_m if after else truth.positions_before_m,
                np.zeros((len(truth.ids), 2, 2)),
                truth.moveable,
                np.array([counts.get(int(i), 0) for i in truth.ids], dtype=np.int64),
            )
        elif topic == TRUE_POSE_TOPIC:
            message = build.odometry(
                bag_ns, ('map', 'base_link'), true_poses[index], true_twists[index], (zeros, zeros)
            )
        elif topic == ODOM_TOPIC:
            message = build.odometry(
                bag_ns,
                ('odom', 'base_link'),
                odometry.poses[index],
                odometry.twists[index],
                odom_cov,
            )
        else:
            frame = run.observations.select(slice(frame_bounds[index], frame_bounds[index + 1]))
            message = build.observations(
                bag_ns,
                frame.landmark_ids,
                np.column_stack([frame.range_m, frame.bearing_rad]),
                frame.covariance,
            )
        yield topic, bag_ns, message


def write_office_bag(
    run: OfficeRun,
    path: Path | str,
    *,
    start_ns: int = DEFAULT_START_NS,
    single_file: bool = False,
    registry: TypeRegistry | None = None,
    progress: Callable[[float, int], None] | None = None,
) -> WrittenBag:
    """Write ``run`` as an mcap bag at ``path`` (.mcap with ``single_file``); BagError."""
    registry = registry if registry is not None else TypeRegistry()
    topics = [
        TopicSpec(topic, msgtype, latched_qos() if latched else output_qos())
        for topic, msgtype, latched in TOPICS
    ]
    return write_bag(
        path,
        topics,
        office_messages(run, registry, start_ns=start_ns),
        registry=registry,
        single_file=single_file,
        progress=None
        if progress is None
        else lambda bag_ns, written: progress((bag_ns - start_ns) / 1e9, written),
    )


def summary(run: OfficeRun, written: WrittenBag) -> str:
    """Return the one-line summary of a written office run."""
    moved = run.landmarks.ids[run.landmarks.moved]
    both = run.seen_at_both_positions.tolist()
    return (
        f'office_sim: wrote {written.path} ({written.size_bytes / 1e6:.2f} MB): seed '
        f'{run.seed} variant {run.variant.value}, {run.duration_s:.1f} s, '
        f'{written.counts[ODOM_TOPIC]} odometry, {written.counts[OBSERVATIONS_TOPIC]} camera '
        f'frames with {len(run.observations)} observations, '
        f'{written.counts[TRUE_LANDMARKS_TOPIC]} ground-truth maps; moveable landmarks seen '
        f'at both positions {len(both)}/{len(moved)} {both}'
        + (
            f'; wall markers moved before the run {run.relocated_ids.tolist()}'
            if len(run.relocated_ids)
            else ''
        )
    )


@console_main('office_sim')
def main(argv: list[str] | None = None) -> int:
    """Simulate one office run and write it as a bag."""
    parser = argparse.ArgumentParser(
        prog='office_sim', description=__doc__, formatter_class=PlainTextHelpFormatter
    )
    parser.add_argument('--seed', type=int, required=True, help='random seed of the run')
    parser.add_argument(
        '--variant',
        default=Variant.STANDARD.value,
        choices=[v.value for v in Variant],
        help='what the moveable markers do',
    )
    parser.add_argument(
        '--output',
        required=True,
        type=Path,
        help='bag directory to create (or .mcap file with --single-file)',
    )
    parser.add_argument('--odom-hz', type=float, default=20.0, help='odometry rate, Hz')
    parser.add_argument(
        '--relocated-static',
        type=int,
        default=0,
        metavar='N',
        help='wall markers moved along their wall by 0.8-1.5 m before the run (0-10): a '
        'later session on a map saved before they moved',
    )
    parser.add_argument(
        '--start-ns',
        type=int,
        default=DEFAULT_START_NS,
        help='bag time of the run start, int ns since the epoch',
    )
    parser.add_argument(
        '--single-file',
        action='store_true',
        help='write one bare .mcap file instead of a bag directory',
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        config = OfficeConfig(
            odom_rate_hz=args.odom_hz, relocated_static_count=args.relocated_static
        )
    except ValueError as err:
        parser.error(str(err))
    run = simulate_office(args.seed, args.variant, config=config)
    reporter = ProgressReporter(run.duration_s, label='office_sim', unit='s')
    written = write_office_bag(
        run,
        args.output,
        start_ns=args.start_ns,
        single_file=args.single_file,
        progress=lambda done_s, items: reporter.update(done_s, items=items),
    )
    reporter.update(run.duration_s, items=sum(written.counts.values()))
    reporter.finish()
    print(summary(run, written))  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
