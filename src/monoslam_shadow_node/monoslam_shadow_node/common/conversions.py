"""Messages <-> the types the three nodes share: feature arrays, camera poses, camera_info.

Design notes: docs/design/monoslam_core.md and monoslam_nodes.md ("The message layer").
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING, STATIC
from monoslam_shadow_node.common.core.inputs import CameraPose, Features
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.geometry import quaternion
from slam_core.stamps import stamp_to_ns

QUATERNION_NORM_TOLERANCE = 1e-3
"""Quaternions within this of unit norm are normalized; others go on as they are, and the
core rejects the resulting matrix as not a rotation (the culprit is named there)."""


MARKER_COLOURS = {
    PENDING: (0.9, 0.1, 0.1),  # red, as the paper's Fig. 4 draws features waiting for a decision
    STATIC: (0.1, 0.3, 0.9),  # blue
    DYNAMIC: (0.1, 0.75, 0.1),  # green
}


CDR_LITTLE_ENDIAN = b'\x00\x01\x00\x00'
"""The encapsulation header of a serialized ROS 2 message: plain CDR, little endian."""


def features_from_message(message: Any) -> Features:
    """Return the ids and raw pixels of a slam_interfaces/FeatureTrackArray."""
    tracks = list(message.tracks)
    ids = np.array([int(track.id) for track in tracks], dtype=np.int64)
    pixels = np.array([(float(track.u), float(track.v)) for track in tracks], dtype=np.float64)
    return Features(
        stamp_to_ns(message.header.stamp),
        str(message.header.frame_id),
        ids,
        pixels.reshape(-1, 2),
    )


FEATURE_TRACK_CDR = np.dtype(
    [('id', '<i8'), ('u', '<f8'), ('v', '<f8'), ('covariance', '<f8', (3,)), ('warp', '<f8', (4,))]
)
"""One slam_interfaces/FeatureTrack in little-endian CDR (id, u, v, covariance[3], warp[4]):
80 bytes, 8-aligned, as in a sequence."""


def tracks_cdr(
    data: bytes, record: np.dtype = FEATURE_TRACK_CDR, stride: int | None = None
) -> tuple[int, str, np.ndarray]:
    """Return stamp (ns), frame id and ``record`` tracks (a read-only view, ``stride`` apart)
    of a header + 8-aligned tracks message; CDR_ERRORS when not plain little-endian CDR."""
    if data[:4] != CDR_LITTLE_ENDIAN:
        raise ValueError('not plain little-endian CDR')
    sec, nanosec, length = struct.unpack_from('<iII', data, 4)
    if length < 1 or data[15 + length] != 0:
        raise ValueError('frame_id is not a NUL-terminated string')
    frame_id = data[16 : 15 + length].decode()
    offset = 16 + length
    offset += -(offset - 4) % 4  # CDR alignment counts from after the encapsulation
    (count,) = struct.unpack_from('<I', data, offset)
    offset += 4
    if count:
        offset += -(offset - 4) % 8
    stride = record.itemsize if stride is None else stride
    if len(data) < offset + stride * count - (stride - record.itemsize):
        raise ValueError('shorter than its tracks')
    tracks = np.ndarray((count,), record, buffer=data, offset=offset, strides=(stride,))
    return sec * 1_000_000_000 + nanosec, frame_id, tracks


def cdr_features(stamp_ns: int, frame_id: str, tracks: np.ndarray) -> Features:
    """Return the Features of FEATURE_TRACK_CDR records (ids and pixels copied out)."""
    pixels = np.column_stack([tracks['u'], tracks['v']]).astype(np.float64)
    return Features(stamp_ns, frame_id, tracks['id'].astype(np.int64), pixels)


def deserialized(data: bytes, deserialize: Callable[[bytes], Any], kind: str = 'features') -> Any:
    """Return ``deserialize(data)``; ValueError naming the size when not a ``kind`` message."""
    try:
        return deserialize(data)
    except Exception as err:  # rclpy raises its RMWError (not exported) for bad bytes
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise ValueError(
            f'a {kind} message of {len(data)} bytes is not a '
            f'slam_interfaces/{CDR_TYPES[kind]} ({reason})'
        ) from None


CDR_TYPES = {'features': 'FeatureTrackArray', 'shadow tracks': 'ShadowTrackArray'}
"""The message type of each kind ``deserialized`` names."""


CDR_ERRORS = (ValueError, IndexError, struct.error, UnicodeDecodeError)


def features_from_cdr(data: bytes, deserialize: Callable[[bytes], Any]) -> Features:
    """Return the Features of a serialized FeatureTrackArray (CDR read directly, else through
    ``deserialize``); ValueError naming the size and reason when it is none."""
    try:
        stamp_ns, frame_id, tracks = tracks_cdr(data)
    except CDR_ERRORS:
        return features_from_message(deserialized(data, deserialize))
    return cdr_features(stamp_ns, frame_id, tracks)


def feature_array_cdr(tracks: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """Return a FeatureTrackArray of FEATURE_TRACK_CDR ``tracks`` as little-endian CDR bytes."""
    tracks = np.ascontiguousarray(tracks, dtype=FEATURE_TRACK_CDR)
    name = frame_id.encode('utf-8') + b'\x00'
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    head = CDR_LITTLE_ENDIAN + struct.pack('<iII', sec, nanosec, len(name)) + name
    head += bytes(-(len(head) - 4) % 4) + struct.pack('<I', len(tracks))
    if len(tracks):
        head += bytes(-(len(head) - 4) % 8)
    return head + tracks.tobytes()


def rotation_from_quaternion(x: float, y: float, z: float, w: float) -> FloatArray:
    """Return the rotation (3, 3) of a quaternion (x, y, z, w), normalized when nearly unit."""
    q = np.array([x, y, z, w], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if math.isfinite(norm) and abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
        q /= norm
    return quaternion.rotation_from_quaternion(q[[3, 0, 1, 2]])  # (w, x, y, z)


def pose_from_message(message: Any) -> CameraPose:
    """Return the CameraPose of a PoseWithCovarianceStamped (ROS covariance order, NaN kept)."""
    pose = message.pose.pose
    q = pose.orientation
    position = pose.position
    covariance = np.asarray(message.pose.covariance, dtype=np.float64).reshape(6, 6)
    return CameraPose(
        stamp_to_ns(message.header.stamp),
        str(message.header.frame_id),
        rotation_from_quaternion(float(q.x), float(q.y), float(q.z), float(q.w)),
        np.array([float(position.x), float(position.y), float(position.z)]),
        covariance if np.any(covariance != 0.0) else None,
    )


def camera_info_key(message: Any) -> tuple[object, ...]:
    """Return what of a sensor_msgs/CameraInfo the filter uses, to detect a change."""
    return (
        int(message.width),
        int(message.height),
        tuple(float(v) for v in message.k),
        tuple(float(v) for v in message.d),
        str(message.distortion_model),
    )


def camera_from_info(message: Any) -> CameraModel:
    """Return the camera model of a sensor_msgs/CameraInfo (ValueError naming the field)."""
    width, height, k, d, model = camera_info_key(message)
    return CameraModel.from_camera_info(width, height, k, d, model)  # type: ignore[arg-type]


def describe_camera(camera: CameraModel) -> str:
    """Return a one-line summary of a camera model for the log."""
    k = camera.K
    return (
        f'{camera.width}x{camera.height} px, fx={k[0, 0]:g} fy={k[1, 1]:g} '
        f'cx={k[0, 2]:g} cy={k[1, 2]:g}, {camera.distortion_model} d={camera.D.tolist()}'
    )


@dataclass(frozen=True, eq=False)
class CameraUpdate:
    """One camera_info's outcome: ``camera`` (None: rejected), ``first`` and the log ``text``."""

    camera: CameraModel | None
    first: bool
    text: str


class CameraInfoWatch:
    """Follows a camera_info topic: change detection, parsing and log lines."""

    def __init__(self, topic: str) -> None:
        self.topic = topic
        self.rejected = 0
        self._key: tuple[object, ...] | None = None

    def update(self, message: Any) -> CameraUpdate | None:
        """Return the update a CameraInfo brings, None if nothing used changed."""
        key = camera_info_key(message)
        if key == self._key:
            return None
        first = self._key is None
        try:
            camera = camera_from_info(message)
        except ValueError as err:
            self.rejected += 1
            kept = 'still waiting for a usable one' if first else 'camera kept'
            return CameraUpdate(None, first, f'{self.topic} rejected ({err}); {kept}')
        self._key = key
        if first:
            return CameraUpdate(camera, True, f'camera: {describe_camera(camera)}')
        text = f'{self.topic} changed: now {describe_camera(camera)} (used from the next frame on)'
        return CameraUpdate(camera, False, text)
