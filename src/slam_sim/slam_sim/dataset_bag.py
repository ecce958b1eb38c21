"""The atomic mcap bag writer and message factory; see docs/design/simulation.md."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from rclpy.qos import QoSProfile
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer, WriterError

from slam_core.errors import BagError
from slam_core.geometry.quaternion import quaternion_from_yaw
from slam_ros.qos import recorded_from_profile
from slam_ros.typesys import TypeRegistry

ODOMETRY_TYPE = 'nav_msgs/msg/Odometry'
OBSERVATIONS_TYPE = 'slam_interfaces/msg/LandmarkObservationArray'
LANDMARK_MAP_TYPE = 'slam_interfaces/msg/LandmarkMap'
INCREMENT_TYPE = 'slam_interfaces/msg/OdometryIncrement'
PROGRESS_EVERY = 2000


@dataclass(frozen=True)
class WrittenBag:
    """A written bag: its path (directory or .mcap), messages per topic and size in bytes."""

    path: Path
    counts: dict[str, int]
    size_bytes: int


@dataclass(frozen=True)
class TopicSpec:
    """One topic of a bag: name, message type and the QoS its publisher offered."""

    name: str
    msgtype: str
    qos: QoSProfile


def check_output(path: Path | str, *, single_file: bool) -> Path:
    """Return ``path`` made absolute; BagError if it exists, has no directory or a wrong suffix."""
    target = Path(path).expanduser().absolute()
    if target.exists():
        raise BagError(f'output {str(target)!r} exists already; remove it or choose another')
    if not target.parent.is_dir():
        raise BagError(f'output {str(target)!r}: directory {str(target.parent)!r} is missing')
    if single_file != (target.suffix == '.mcap'):
        raise BagError(
            f'output {str(target)!r}: a single-file bag must end in .mcap and a bag '
            'directory must not; use --single-file for a .mcap file'
        )
    return target


def write_bag(
    path: Path | str,
    topics: Sequence[TopicSpec],
    messages: Iterable[tuple[str, int, Any]],
    *,
    registry: TypeRegistry,
    single_file: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> WrittenBag:
    """Write (topic, bag stamp ns, message) items as a bag at ``path`` atomically; BagError."""
    target = check_output(path, single_file=single_file)
    staging_root = target.parent / f'.{target.name}.writing-{os.getpid()}'
    staging = staging_root / (target.stem if single_file else target.name)
    counts = {topic.name: 0 for topic in topics}
    written = 0
    try:
        staging_root.mkdir()
        writer = Writer(staging, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        with writer:
            connections = {
                topic.name: registry.add_connection(
                    writer, topic.name, topic.msgtype, [recorded_from_profile(topic.qos)]
                )
                for topic in topics
            }
            for name, bag_ns, message in messages:
                data = registry.typestore.serialize_cdr(message, message.__msgtype__)
                writer.write(connections[name], bag_ns, bytes(data))
                counts[name] += 1
                written += 1
                if progress is not None and written % PROGRESS_EVERY == 0:
                    progress(bag_ns, written)
        if single_file:
            (staging / f'{staging.name}.mcap').rename(target)
        else:
            staging.rename(target)
    except (OSError, WriterError) as err:
        raise BagError(f'output {str(target)!r} cannot be written: {err}') from None
    finally:
        shutil.rmtree(staging_root, ignore_errors=True)
    size = (
        target.stat().st_size if single_file else sum(p.stat().st_size for p in target.iterdir())
    )
    return WrittenBag(path=target, counts=counts, size_bytes=size)


class CameraInfoLike(Protocol):
    """The sensor_msgs/CameraInfo fields a simulated camera provides (k, r, p row-major)."""

    @property
    def height(self) -> int: ...
    @property
    def width(self) -> int: ...
    @property
    def distortion_model(self) -> str: ...
    @property
    def d(self) -> Any: ...
    @property
    def k(self) -> Any: ...
    @property
    def r(self) -> Any: ...
    @property
    def p(self) -> Any: ...


class MessageFactory:
    """Builds rosbags message objects; the registry must know every type used."""

    def __init__(self, registry: TypeRegistry, msgtypes: Iterable[str]) -> None:
        for msgtype in msgtypes:
            registry.ensure(msgtype)
        self.types: dict[str, Any] = registry.typestore.types

    def _type(self, msgtype: str) -> Any:
        return self.types[msgtype]

    def stamp(self, stamp_ns: int) -> Any:
        """Return a builtin_interfaces/Time of int nanoseconds."""
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        return self._type('builtin_interfaces/msg/Time')(sec=sec, nanosec=nanosec)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        """Return a std_msgs/Header."""
        return self._type('std_msgs/msg/Header')(stamp=self.stamp(stamp_ns), frame_id=frame_id)

    def camera_info(self, stamp_ns: int, frame_id: str, info: CameraInfoLike) -> Any:
        """Return a sensor_msgs/CameraInfo of ``info``'s fields (no binning, full-image ROI)."""
        return self._type('sensor_msgs/msg/CameraInfo')(
            header=self.header(stamp_ns, frame_id),
            height=info.height,
            width=info.width,
            distortion_model=info.distortion_model,
            d=info.d,
            k=info.k,
            r=info.r,
            p=info.p,
            binning_x=0,
            binning_y=0,
            roi=self._type('sensor_msgs/msg/RegionOfInterest')(
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
            ),
        )

    def odometry(
        self,
        stamp_ns: int,
        frames: tuple[str, str],
        pose: np.ndarray,
        twist: np.ndarray,
        covariances: tuple[np.ndarray, np.ndarray],
    ) -> Any:
        """Return an Odometry: pose (x m, y m, theta rad), twist (m/s, rad/s), 36-vectors."""
        geometry = 'geometry_msgs/msg/'
        point = self._type(geometry + 'Point')(x=float(pose[0]), y=float(pose[1]), z=0.0)
        x, y, z, w = quaternion_from_yaw(float(pose[2]))
        orientation = self._type(geometry + 'Quaternion')(x=x, y=y, z=z, w=w)
        vector = self._type(geometry + 'Vector3')
        body_twist = self._type(geometry + 'Twist')(
            linear=vector(x=float(twist[0]), y=0.0, z=0.0),
            angular=vector(x=0.0, y=0.0, z=float(twist[1])),
        )
        return self._type(ODOMETRY_TYPE)(
            header=self.header(stamp_ns, frames[0]),
            child_frame_id=frames[1],
            pose=self._type(geometry + 'PoseWithCovariance')(
                pose=self._type(geometry + 'Pose')(position=point, orientation=orientation),
                covariance=covariances[0],
            ),
            twist=self._type(geometry + 'TwistWithCovariance')(
                twist=body_twist, covariance=covariances[1]
            ),
        )

    def observations(
        self,
        stamp_ns: int,
        landmark_ids: np.ndarray,
        range_bearing: np.ndarray,
        covariances: np.ndarray,
    ) -> Any:
        """Return a LandmarkObservationArray: ids (n,), (m, rad) (n, 2), covariances (n, 2, 2)."""
        item = self._type('slam_interfaces/msg/LandmarkObservation')
        return self._type(OBSERVATIONS_TYPE)(
            header=self.header(stamp_ns, 'base_link'),
            observations=[
                item(
                    landmark_id=int(landmark_id),
                    range_m=float(z[0]),
                    bearing_rad=float(z[1]),
                    covariance=np.asarray(cov, dtype=np.float64).reshape(4),
                )
                for landmark_id, z, cov in zip(
                    landmark_ids, range_bearing, covariances, strict=True
                )
            ],
        )

    def landmark_map(
        self,
        stamp_ns: int,
        landmark_ids: np.ndarray,
        positions: np.ndarray,
        covariances: np.ndarray,
        moveable: np.ndarray,
        num_observations: np.ndarray,
    ) -> Any:
        """Return a LandmarkMap: ids (L,), positions (L, 2) m, covariances (L, 2, 2) m^2."""
        point = self._type('geometry_msgs/msg/Point')
        estimate = self._type('slam_interfaces/msg/LandmarkEstimate')
        return self._type(LANDMARK_MAP_TYPE)(
            header=self.header(stamp_ns, 'map'),
            landmarks=[
                estimate(
                    landmark_id=int(landmark_ids[k]),
                    position=point(x=float(positions[k, 0]), y=float(positions[k, 1]), z=0.0),
                    covariance=np.asarray(covariances[k], dtype=np.float64).reshape(4),
                    weight=1.0,
                    moveable=bool(moveable[k]),
                    num_observations=int(num_observations[k]),
                )
                for k in range(len(landmark_ids))
            ],
        )

    def increment(
        self,
        stamps_ns: tuple[int, int],
        u: np.ndarray,
        covariance: np.ndarray,
        odom_poses: tuple[np.ndarray, np.ndarray],
    ) -> Any:
        """Return an OdometryIncrement: eq. 2 u (3,), covariance (3, 3), poses in ``odom``."""
        return self._type(INCREMENT_TYPE)(
            header=self.header(stamps_ns[1], 'base_link'),
            stamp_from=self.stamp(stamps_ns[0]),
            stamp_to=self.stamp(stamps_ns[1]),
            forward_m=float(u[0]),
            side_m=float(u[1]),
            angular_rad=float(u[2]),
            covariance=np.asarray(covariance, dtype=np.float64).reshape(9),
            odom_frame_id='odom',
            odom_pose_from=np.asarray(odom_poses[0], dtype=np.float64),
            odom_pose_to=np.asarray(odom_poses[1], dtype=np.float64),
            reset=False,
        )
