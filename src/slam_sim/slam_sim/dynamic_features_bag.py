"""dynamic_features_sim: tracked image features of a hand-held camera among moving objects.

Ideal tracks (true ids) of the dynamic scene (docs/design/simulation.md). Topics:
  /camera/camera_info (sensor_msgs/CameraInfo), /camera/pose (true, zero covariance)
  /features (slam_interfaces/FeatureTrackArray): noisy raw pixels by track id
  /ground_truth/features (slam_interfaces/ShadowTrackArray, map): status, position, velocity
An output ending in .mcap is one file, any other path a bag directory."""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.cli import PlainTextHelpFormatter, console_main
from slam_core.errors import BagError
from slam_core.geometry.quaternion import quaternion_from_rotation
from slam_core.progress import ProgressReporter
from slam_ros.qos import output_qos
from slam_ros.typesys import TypeRegistry
from slam_sim.core.dynamic_config import MOTION_KINDS, DynamicSceneConfig
from slam_sim.core.dynamic_scene import (
    DEFAULT_START_NS,
    DynamicSceneRun,
    FeatureFrame,
    simulate_dynamic_scene,
)
from slam_sim.dataset_bag import MessageFactory, TopicSpec, WrittenBag, write_bag

CAMERA_INFO_TOPIC = '/camera/camera_info'
CAMERA_POSE_TOPIC = '/camera/pose'
FEATURES_TOPIC = '/features'
TRUE_FEATURES_TOPIC = '/ground_truth/features'
CAMERA_INFO_TYPE = 'sensor_msgs/msg/CameraInfo'
POSE_TYPE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
FEATURES_TYPE = 'slam_interfaces/msg/FeatureTrackArray'
SHADOW_TRACKS_TYPE = 'slam_interfaces/msg/ShadowTrackArray'
MAP_FRAME, OPTICAL_FRAME = 'map', 'camera_optical_frame'
# (topic, type) in the order of the messages at one stamp.
TOPICS = (
    (CAMERA_INFO_TOPIC, CAMERA_INFO_TYPE),
    (CAMERA_POSE_TOPIC, POSE_TYPE),
    (FEATURES_TOPIC, FEATURES_TYPE),
    (TRUE_FEATURES_TOPIC, SHADOW_TRACKS_TYPE),
)


class _Messages:
    """Builds one frame's messages."""

    def __init__(self, registry: TypeRegistry, run: DynamicSceneRun) -> None:
        self.build = MessageFactory(registry, [msgtype for _, msgtype in TOPICS])
        self.types, self.run = self.build.types, run
        self.info = run.camera.camera_info()

    def _point(self, xyz: np.ndarray, kind: str = 'Point') -> Any:
        x, y, z = (float(value) for value in xyz)
        return self.types[f'geometry_msgs/msg/{kind}'](x=x, y=y, z=z)

    def camera_info(self, stamp_ns: int) -> Any:
        """Return the CameraInfo of the run's camera."""
        return self.build.camera_info(stamp_ns, OPTICAL_FRAME, self.info)

    def pose(self, frame: FeatureFrame) -> Any:
        """Return the true optical-frame pose in map, zero covariance."""
        w, x, y, z = quaternion_from_rotation(frame.camera_rotation).tolist()
        geometry = 'geometry_msgs/msg/'
        pose = self.types[geometry + 'Pose'](
            position=self._point(frame.camera_position),
            orientation=self.types[geometry + 'Quaternion'](x=x, y=y, z=z, w=w),
        )
        return self.types[POSE_TYPE](
            header=self.build.header(frame.stamp_ns, MAP_FRAME),
            pose=self.types[geometry + 'PoseWithCovariance'](pose=pose, covariance=np.zeros(36)),
        )

    def features(self, frame: FeatureFrame) -> Any:
        """Return the noisy raw pixels of the frame's tracks."""
        track = self.types['slam_interfaces/msg/FeatureTrack']
        return self.types[FEATURES_TYPE](
            header=self.build.header(frame.stamp_ns, OPTICAL_FRAME),
            tracks=[
                track(id=track_id, u=u, v=v, covariance=np.zeros(3), warp=np.zeros(4))
                for track_id, (u, v) in zip(
                    frame.track_ids.tolist(), frame.pixels.tolist(), strict=True
                )
            ],
        )

    def truth(self, index: int, frame: FeatureFrame) -> Any:
        """Return the frame's tracks with their true status, position and velocity in map."""
        track = self.types['slam_interfaces/msg/ShadowTrack']
        positions = self.run.point_positions[index, frame.point_ids]
        velocities = self.run.point_velocities[index, frame.point_ids]
        moving = self.run.point_moving[frame.point_ids].tolist()
        return self.types[SHADOW_TRACKS_TYPE](
            header=self.build.header(frame.stamp_ns, MAP_FRAME),
            tracks=[
                track(
                    id=int(frame.track_ids[n]),
                    status=track.DYNAMIC if moving[n] else track.STATIC,
                    position=self._point(positions[n]),
                    position_covariance=np.zeros(9),
                    velocity=self._point(velocities[n], 'Vector3'),
                    velocity_covariance=np.zeros(9),
                    test_statistic=math.nan,
                    test_dof=0,
                )
                for n in range(len(frame.track_ids))
            ],
        )


def dynamic_features_messages(
    run: DynamicSceneRun,
    registry: TypeRegistry,
    *,
    progress: Callable[[float, int], None] | None = None,
) -> Iterator[tuple[str, int, Any]]:
    """Yield (topic, bag stamp ns, message) of every frame in stamp order; progress per frame."""
    build = _Messages(registry, run)
    start_ns = run.frames[0].stamp_ns
    for index, frame in enumerate(run.frames):
        stamp_ns = frame.stamp_ns
        yield CAMERA_INFO_TOPIC, stamp_ns, build.camera_info(stamp_ns)
        yield CAMERA_POSE_TOPIC, stamp_ns, build.pose(frame)
        yield FEATURES_TOPIC, stamp_ns, build.features(frame)
        yield TRUE_FEATURES_TOPIC, stamp_ns, build.truth(index, frame)
        if progress is not None:
            progress((stamp_ns - start_ns) / 1e9, index + 1)


def _check_replaceable(target: Path) -> None:
    """Raise BagError unless ``target`` is a bag: an .mcap file or a rosbag2 directory."""
    if target.is_file() and not target.is_symlink() and target.suffix == '.mcap':
        return
    names = {p.name for p in target.iterdir()} if target.is_dir() else set()
    bag_files = {n for n in names if n.endswith(('.mcap', '.db3'))}
    if 'metadata.yaml' not in names or names - bag_files - {'metadata.yaml'}:
        raise BagError(
            f'output {str(target)!r} exists and is not a bag; --force only replaces bags'
        )


def write_dynamic_features_bag(
    run: DynamicSceneRun,
    path: Path | str,
    *,
    force: bool = False,
    registry: TypeRegistry | None = None,
    progress: Callable[[float, int], None] | None = None,
) -> WrittenBag:
    """Write ``run`` as a bag at ``path``; ``force`` replaces a bag once complete; BagError."""
    registry = registry if registry is not None else TypeRegistry()
    target = Path(path).expanduser().absolute()
    single_file = target.suffix == '.mcap'
    topics = [TopicSpec(topic, msgtype, output_qos()) for topic, msgtype in TOPICS]

    def write(to: Path) -> WrittenBag:
        messages = dynamic_features_messages(run, registry, progress=progress)
        return write_bag(to, topics, messages, registry=registry, single_file=single_file)

    if not target.exists():
        return write(target)
    if not force:
        raise BagError(f'output {str(target)!r} exists already; remove it or pass --force')
    _check_replaceable(target)
    staging_root = target.parent / f'.{target.name}.replacing-{os.getpid()}'
    try:
        staging_root.mkdir()
        written = write(staging_root / target.name)
        if target.is_dir():
            shutil.rmtree(target)
        else:
            target.unlink()
        written.path.rename(target)
    except OSError as err:
        raise BagError(f'output {str(target)!r} cannot be replaced: {err}') from None
    finally:
        shutil.rmtree(staging_root, ignore_errors=True)
    return WrittenBag(path=target, counts=written.counts, size_bytes=written.size_bytes)


def summary(run: DynamicSceneRun, written: WrittenBag, elapsed_s: float) -> str:
    """Return the summary of a written bag: frames, tracks, visible features, size."""
    moving_tracks = sum(bool(run.point_moving[p]) for p in run.track_point.values())
    per_frame = np.array(
        [[np.count_nonzero(~run.point_moving[f.point_ids]), f.point_ids.size] for f in run.frames]
    )
    static, total = per_frame.mean(axis=0)
    config = run.config
    return (
        f'dynamic_features_sim: wrote {written.path} ({written.size_bytes / 1e6:.2f} MB) in '
        f'{elapsed_s:.1f} s: seed {run.seed}, {len(run.frames)} frames at {config.rate_hz:g} Hz, '
        f'focal {config.focal_px:g} px, noise {config.pixel_noise_px:g} px; '
        f'{np.count_nonzero(~run.point_moving)} static and {np.count_nonzero(run.point_moving)} '
        f'moving points ({", ".join(run.object_motion) or "no objects"}); '
        f'{len(run.track_point)} tracks ({len(run.track_point) - moving_tracks} static, '
        f'{moving_tracks} moving); {total:.1f} features per frame ({static:.1f} static, '
        f'{total - static:.1f} moving)'
    )


def add_loop_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--loop-away-s`` (``DynamicSceneConfig.loop_away_s``) to ``parser``."""
    defaults = DynamicSceneConfig()
    parser.add_argument(
        '--loop-away-s',
        type=float,
        default=defaults.loop_away_s,
        help=f'a loop scene: from {defaults.loop_start_s:g} s the camera turns '
        f'{defaults.loop_angle_deg:g} deg away from the start area for this long and back '
        '(0: none)',
    )


def _parser() -> argparse.ArgumentParser:
    defaults = DynamicSceneConfig()
    parser = argparse.ArgumentParser(
        prog='dynamic_features_sim',
        description=__doc__,
        formatter_class=PlainTextHelpFormatter,
    )
    parser.add_argument('--seed', type=int, required=True, help='random seed of the run')
    parser.add_argument(
        '--output', required=True, type=Path, help='PATH.mcap (one file) or a bag directory'
    )
    parser.add_argument('--force', action='store_true', help='replace an existing bag')
    parser.add_argument(
        '--duration-s', type=float, default=defaults.duration_s, help='run length, s'
    )
    parser.add_argument('--rate-hz', type=float, default=defaults.rate_hz, help='frame rate, Hz')
    parser.add_argument(
        '--focal-px', type=float, default=defaults.focal_px, help='focal length, px (150-500)'
    )
    parser.add_argument(
        '--pixel-noise-px',
        type=float,
        default=defaults.pixel_noise_px,
        help='pixel noise std per coordinate, px',
    )
    parser.add_argument(
        '--motions',
        default=','.join(defaults.motions),
        help=f'object motion kinds, cycled over the {defaults.objects} objects; comma list of '
        f'{", ".join(MOTION_KINDS)}',
    )
    add_loop_argument(parser)
    parser.add_argument(
        '--start-ns',
        type=int,
        default=DEFAULT_START_NS,
        help='bag time of the first frame, int ns since the epoch',
    )
    return parser


def _config(parser: argparse.ArgumentParser, args: argparse.Namespace) -> DynamicSceneConfig:
    """Return the config of the options; a bad value exits naming its option."""
    try:
        return DynamicSceneConfig(
            duration_s=args.duration_s,
            rate_hz=args.rate_hz,
            focal_px=args.focal_px,
            pixel_noise_px=args.pixel_noise_px,
            motions=tuple(kind.strip() for kind in args.motions.split(',') if kind.strip()),
            loop_away_s=args.loop_away_s,
        )
    except ValueError as err:
        option = '--' + str(err).split(' ', 1)[0].replace('_', '-')
        parser.error(f'{option}: {err}')


@console_main('dynamic_features_sim')
def main(argv: list[str] | None = None) -> int:
    """Simulate one dynamic-scene run and write its features and ground truth as a bag."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    config = _config(parser, args)
    reporter = ProgressReporter(config.duration_s, label='dynamic_features_sim', unit='s')
    run = simulate_dynamic_scene(args.seed, config, start_ns=args.start_ns)
    written = write_dynamic_features_bag(
        run,
        args.output,
        force=args.force,
        progress=lambda done_s, frames: reporter.update(done_s, items=frames * len(TOPICS)),
    )
    reporter.update(config.duration_s, items=sum(written.counts.values()))
    reporter.finish()
    print(summary(run, written, reporter.clock() - reporter.started))  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
