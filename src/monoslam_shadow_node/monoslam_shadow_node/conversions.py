"""Messages <-> Shadow filter core types. Fields are read by name, so rclpy messages and
rosbags-deserialized messages both work; output messages are filled from factories (the
message classes) passed in, as marker_detector's conversions do.

Pose covariance. geometry_msgs/PoseWithCovariance orders its 6x6 covariance (row-major) as
(x, y, z, rotation about X, rotation about Y, rotation about Z) in a fixed-axis
representation: the rotations are small angles about the axes of the pose's parent frame
(header.frame_id, the world). The core (``FrameInput.pose_covariance``, ``rays.View``) wants
(position m, rotation rad about the world axes), the rotation error entering as
R = exp([dtheta]x) R_hat. That is the same order and the same convention, so the matrix is
passed on unchanged (no reordering). A publisher that fills the rotation block with
roll-pitch-yaw variances instead matches this only near the identity orientation. An
all-zero covariance means a known pose.

No NaN leaves this module (``track_fields``):

- a position whose depth is not known yet (``TrackReport.defined`` false: the inverse depth
  is not 3 sigma above zero; never for STATIC, which carries the handover) is published as
  the core reports it, a point on the viewing ray 1000 m from the camera (finite; it carries
  the bearing), with ``position_covariance`` set to ``UNKNOWN_COVARIANCE``: -1 in element 0
  and zeros elsewhere, the sensor_msgs convention (e.g. sensor_msgs/Imu) for "no estimate";
- before a feature's first test, ``test_statistic`` is ``NO_TEST_STATISTIC`` (-1.0, a value
  the chi-square statistic T >= 0 never takes) and ``test_dof`` is 0;
- any other non-finite number (a core fault) is never published: a non-finite covariance or
  velocity becomes ``UNKNOWN_COVARIANCE`` (velocity 0), and a track or handover with a
  non-finite position is left out (``track_fields`` returns None).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from monoslam_shadow_node.core.shadow_filter import FrameInput, Handover, TrackReport
from monoslam_shadow_node.core.shadow_track import DYNAMIC, PENDING, STATIC
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.geometry import quaternion
from slam_core.stamps import ns_to_stamp, stamp_to_ns

UNKNOWN_COVARIANCE = (-1.0, *([0.0] * 8))
"""A 3x3 covariance with no estimate: element 0 is -1 (sensor_msgs convention)."""
NO_TEST_STATISTIC = -1.0
"""test_statistic of a feature that has not been tested yet (test_dof is then 0)."""
QUATERNION_NORM_TOLERANCE = 1e-3
"""Quaternions within this of unit norm are normalized; others go on as they are, and the
core rejects the resulting matrix as not a rotation (the culprit is named there)."""
STATIC_MARKER_LIMIT = 5000
"""At most this many handed-over (static) features are drawn, the most recent ones."""
MARKER_SPHERE_M = 0.08
MARKER_LINE_M = 0.02
MARKER_COLOURS = {
    PENDING: (0.9, 0.1, 0.1),  # red, as the paper's Fig. 4 draws features waiting for a decision
    STATIC: (0.1, 0.3, 0.9),  # blue
    DYNAMIC: (0.1, 0.75, 0.1),  # green
}
MARKER_NAMESPACES = {PENDING: 'pending', STATIC: 'static', DYNAMIC: 'dynamic'}
TRAJECTORY_NAMESPACE = 'dynamic_trajectories'
_CDR_LITTLE_ENDIAN = b'\x00\x01\x00\x00'
"""The encapsulation header of a serialized ROS 2 message: plain CDR, little endian."""


@dataclass(frozen=True, eq=False)
class Features:
    """One FeatureTrackArray: image stamp (int ns), camera frame, track ids (M,) and raw
    pixels (M, 2) (u right, v down; may hold NaN, the core drops those)."""

    stamp_ns: int
    frame_id: str
    ids: IntArray
    pixels: FloatArray


@dataclass(frozen=True, eq=False)
class CameraPose:
    """One PoseWithCovarianceStamped of the camera optical frame: stamp (int ns), world frame
    (header.frame_id), R_world_camera (3, 3), optical centre (3,) m, and the covariance
    (6, 6) over (position, rotation about the world axes), None when all zero; and when the
    source gives them (``pose_links``), the covariances (K, 6, 6) of the pose's error with
    those of its earlier poses stamped ``cross_stamps``."""

    stamp_ns: int
    frame_id: str
    rotation: FloatArray
    centre: FloatArray
    covariance: FloatArray | None
    cross_stamps: tuple[int, ...] = ()
    cross_covariances: FloatArray | None = None


@dataclass(frozen=True)
class TrackFields:
    """The finite numbers of one ShadowTrack: id, status, position (3) m and covariance (9),
    velocity (3) m/s and covariance (9), test statistic and its degrees of freedom."""

    id: int
    status: int
    position: tuple[float, float, float]
    position_covariance: tuple[float, ...]
    velocity: tuple[float, float, float]
    velocity_covariance: tuple[float, ...]
    test_statistic: float
    test_dof: int


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
    """Return the stamp (ns), frame id and tracks (``record`` records ``stride`` bytes apart,
    default its size: a read-only view of ``data``) of a serialized message of a header and
    a sequence of 8-aligned tracks (FeatureTrackArray, ShadowTrackArray); ValueError (or
    IndexError, struct.error, UnicodeDecodeError) when the bytes are not plain little-endian
    CDR of one."""
    if data[:4] != _CDR_LITTLE_ENDIAN:
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


def _cdr_features(stamp_ns: int, frame_id: str, tracks: np.ndarray) -> Features:
    """Return the Features of FEATURE_TRACK_CDR records (ids and pixels copied out)."""
    pixels = np.column_stack([tracks['u'], tracks['v']]).astype(np.float64)
    return Features(stamp_ns, frame_id, tracks['id'].astype(np.int64), pixels)


def deserialized(data: bytes, deserialize: Callable[[bytes], Any], kind: str = 'features') -> Any:
    """Return ``deserialize(data)``; ValueError naming the bytes' size when they are no
    message of the ``kind``'s type at all."""
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
    """Return ``features_from_message`` of a serialized slam_interfaces/FeatureTrackArray,
    read straight from its CDR bytes (plain CDR, little endian, as every ROS 2 middleware
    on this machine sends it): deserializing 150 tracks into message objects takes longer
    than reading them. Anything else (another encapsulation, bytes that do not fit) goes
    through ``deserialize`` (bytes -> message) and ``features_from_message``; ValueError
    naming their size and the reason when the bytes are no such message at all."""
    try:
        stamp_ns, frame_id, tracks = tracks_cdr(data)
    except CDR_ERRORS:
        return features_from_message(deserialized(data, deserialize))
    return _cdr_features(stamp_ns, frame_id, tracks)


def predictions_from_cdr(
    data: bytes, deserialize: Callable[[bytes], Any]
) -> tuple[Features, FloatArray, FloatArray]:
    """Return the predicted pixels of a serialized FeatureTrackArray (``features_from_cdr``)
    with their covariances (K, 2, 2) and warps (K, 2, 2) (``prediction_covariances``,
    ``prediction_warps``), read from the bytes the same way."""
    try:
        stamp_ns, frame_id, tracks = tracks_cdr(data)
    except CDR_ERRORS:
        message = deserialized(data, deserialize)
        return (
            features_from_message(message),
            prediction_covariances(message),
            prediction_warps(message),
        )
    features = _cdr_features(stamp_ns, frame_id, tracks)
    return features, _covariances_2x2(tracks['covariance']), tracks['warp'].reshape(-1, 2, 2)


def feature_array_cdr(tracks: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """Return a slam_interfaces/FeatureTrackArray serialized (little-endian CDR, the layout
    ``features_from_cdr`` reads; the bytes rclpy makes of that message): header = stamp and
    frame id, ``tracks`` FEATURE_TRACK_CDR records. Built in one numpy array instead of a
    Python object per track."""
    tracks = np.ascontiguousarray(tracks, dtype=FEATURE_TRACK_CDR)
    name = frame_id.encode('utf-8') + b'\x00'
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    head = _CDR_LITTLE_ENDIAN + struct.pack('<iII', sec, nanosec, len(name)) + name
    head += bytes(-(len(head) - 4) % 4) + struct.pack('<I', len(tracks))
    if len(tracks):
        head += bytes(-(len(head) - 4) % 8)
    return head + tracks.tobytes()


def _covariances_2x2(upper: FloatArray) -> FloatArray:
    """Return the covariances (K, 2, 2) of FeatureTrack.covariance rows (K, 3) [uu, uv, vv]."""
    upper = np.asarray(upper, dtype=np.float64).reshape(-1, 3)
    covariances = np.empty((len(upper), 2, 2))
    covariances[:, 0, 0], covariances[:, 1, 1] = upper[:, 0], upper[:, 2]
    covariances[:, 0, 1] = covariances[:, 1, 0] = upper[:, 1]
    return covariances


def prediction_covariances(message: Any) -> FloatArray:
    """Return the covariances (K, 2, 2), px^2, of a slam_interfaces/FeatureTrackArray's
    predicted pixels (FeatureTrack.covariance [uu, uv, vv]; zeros where not given)."""
    return _covariances_2x2(
        np.array([list(track.covariance) for track in message.tracks], dtype=np.float64)
    )


def prediction_warps(message: Any) -> FloatArray:
    """Return the template warps (K, 2, 2) of a slam_interfaces/FeatureTrackArray's predicted
    pixels (FeatureTrack.warp, row-major; zeros where not given)."""
    warps = np.array([list(track.warp) for track in message.tracks], dtype=np.float64)
    return warps.reshape(-1, 2, 2)


def rotation_from_quaternion(x: float, y: float, z: float, w: float) -> FloatArray:
    """Return the rotation matrix (3, 3) of a quaternion (x, y, z, w).

    A quaternion within ``QUATERNION_NORM_TOLERANCE`` of unit norm is normalized first;
    otherwise (zero, NaN, far from unit) the matrix is returned unnormalized or non-finite,
    for the core to reject with its reason.
    """
    q = np.array([x, y, z, w], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if math.isfinite(norm) and abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
        q /= norm
    return quaternion.rotation_from_quaternion(q[[3, 0, 1, 2]])  # (w, x, y, z)


def pose_from_message(message: Any) -> CameraPose:
    """Return the camera pose of a geometry_msgs/PoseWithCovarianceStamped (the pose of the
    camera optical frame in header.frame_id). The covariance is passed on in ROS order (see
    the module docstring); non-finite values are kept for the core to reject."""
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
    """What one camera_info brought: a usable camera (``camera``; ``first``: none was
    accepted before, else it changed) or a rejection (``camera`` None); ``text`` is the
    line to log."""

    camera: CameraModel | None
    first: bool
    text: str


class CameraInfoWatch:
    """Follows a camera_info topic for a node whose filter needs the camera: one place for
    the change detection, the parsing and the log lines of every such node."""

    def __init__(self, topic: str) -> None:
        self.topic = topic
        self.rejected = 0
        self._key: tuple[object, ...] | None = None

    def update(self, message: Any) -> CameraUpdate | None:
        """Return the update a sensor_msgs/CameraInfo brings, or None if nothing the filter
        uses changed. A rejected one leaves the accepted camera as it was (and is counted in
        ``rejected``)."""
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


def frame_input(features: Features, pose: CameraPose) -> FrameInput:
    """Return the core's input for one image: the features at their own stamp, with the
    pose paired with them."""
    return FrameInput(
        features.stamp_ns, pose.rotation, pose.centre, features.ids, features.pixels,
        pose.covariance, pose.cross_stamps, pose.cross_covariances,
    )  # fmt: skip


def _finite_vector(values: FloatArray) -> tuple[float, float, float] | None:
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if array.size != 3 or not np.all(np.isfinite(array)):
        return None
    return (float(array[0]), float(array[1]), float(array[2]))


def _finite_covariance(values: FloatArray) -> tuple[float, ...] | None:
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if array.size != 9 or not np.all(np.isfinite(array)):
        return None
    return tuple(float(v) for v in array)


def track_fields(report: TrackReport) -> TrackFields | None:
    """Return a track's message fields with no NaN (module docstring), None when its
    position is not finite."""
    position = _finite_vector(report.position)
    if position is None:
        return None
    known = report.defined or report.status == STATIC  # STATIC: the handover's triangulation
    covariance = _finite_covariance(report.position_covariance) if known else None
    velocity = _finite_vector(report.velocity)
    velocity_covariance = _finite_covariance(report.velocity_covariance)
    if velocity is None or velocity_covariance is None:
        velocity, velocity_covariance = (0.0, 0.0, 0.0), UNKNOWN_COVARIANCE
    tested = math.isfinite(report.test_statistic)
    return TrackFields(
        id=int(report.id),
        status=int(report.status),
        position=position,
        position_covariance=covariance if covariance is not None else UNKNOWN_COVARIANCE,
        velocity=velocity,
        velocity_covariance=velocity_covariance,
        test_statistic=float(report.test_statistic) if tested else NO_TEST_STATISTIC,
        test_dof=int(report.test_dof) if tested else 0,
    )


def handover_fields(handover: Handover, statistic: float, dof: int) -> TrackFields | None:
    """Return a handover's message fields (STATIC, zero velocity with zero covariance, the
    deciding test's statistic), None when its position or covariance is not finite."""
    position = _finite_vector(handover.position)
    covariance = _finite_covariance(handover.position_covariance)
    if position is None or covariance is None:
        return None
    tested = math.isfinite(statistic)
    return TrackFields(
        id=int(handover.id),
        status=STATIC,
        position=position,
        position_covariance=covariance,
        velocity=(0.0, 0.0, 0.0),
        velocity_covariance=(0.0,) * 9,
        test_statistic=float(statistic) if tested else NO_TEST_STATISTIC,
        test_dof=int(dof) if tested else 0,
    )


def fill_track(fields: TrackFields, message: Any) -> Any:
    """Fill a slam_interfaces/ShadowTrack from ``fields`` and return it."""
    message.id = fields.id
    message.status = fields.status
    message.position.x, message.position.y, message.position.z = fields.position
    message.position_covariance = list(fields.position_covariance)
    message.velocity.x, message.velocity.y, message.velocity.z = fields.velocity
    message.velocity_covariance = list(fields.velocity_covariance)
    message.test_statistic = fields.test_statistic
    message.test_dof = fields.test_dof
    return message


def fill_track_array(
    fields: Iterable[TrackFields],
    stamp_ns: int,
    frame_id: str,
    message: Any,
    make_track: Callable[[], Any],
) -> Any:
    """Fill a slam_interfaces/ShadowTrackArray and return it; ``make_track`` constructs an
    empty ShadowTrack (the message class)."""
    ns_to_stamp(stamp_ns, message.header.stamp)
    message.header.frame_id = frame_id
    message.tracks = [fill_track(item, make_track()) for item in fields]
    return message


_SHADOW_TRACK_CDR = np.dtype(
    {
        'names': [
            'id', 'status', 'position', 'position_covariance', 'velocity',
            'velocity_covariance', 'test_statistic', 'test_dof',
        ],
        'formats': ['<i8', 'u1', ('<f8', 3), ('<f8', 9), ('<f8', 3), ('<f8', 9), '<f8', '<u4'],
        'offsets': [0, 8, 16, 40, 112, 136, 208, 216],
        'itemsize': 224,
    }
)  # fmt: skip
"""One slam_interfaces/ShadowTrack in CDR, 8-byte aligned as in a sequence: 220 bytes of
fields and 4 of padding before the next one (none after the last)."""


def track_array_cdr(
    reports: Sequence[TrackReport], stamp_ns: int, frame_id: str
) -> tuple[bytes, list[int]]:
    """Return a slam_interfaces/ShadowTrackArray of a frame's tracks, serialized (CDR, what
    rclpy's publish of the message filled by ``track_fields`` and ``fill_track_array``
    sends), and the ids of the tracks left out (their position is not finite:
    ``track_fields`` returns None for them). The rules of ``track_fields`` are evaluated for
    all tracks at once and the bytes written from one structured array: a Python message
    object per track cost more than the Shadow filter's own work per frame."""
    count = len(reports)
    status = np.array([r.status for r in reports], dtype=np.int64).reshape(count)
    position = np.array([r.position for r in reports], dtype=np.float64).reshape(count, 3)
    covariance = np.array([r.position_covariance for r in reports], dtype=np.float64)
    covariance = covariance.reshape(count, 9)
    velocity = np.array([r.velocity for r in reports], dtype=np.float64).reshape(count, 3)
    velocity_covariance = np.array([r.velocity_covariance for r in reports], dtype=np.float64)
    velocity_covariance = velocity_covariance.reshape(count, 9)
    statistic = np.array([r.test_statistic for r in reports], dtype=np.float64).reshape(count)
    defined = np.array([r.defined for r in reports], dtype=bool).reshape(count)
    # the rules of track_fields (module docstring)
    known = defined | (status == STATIC)
    covariance[~(known & np.all(np.isfinite(covariance), axis=1))] = UNKNOWN_COVARIANCE
    moving = np.all(np.isfinite(velocity), axis=1) & np.all(
        np.isfinite(velocity_covariance), axis=1
    )
    velocity[~moving] = 0.0
    velocity_covariance[~moving] = UNKNOWN_COVARIANCE
    tested = np.isfinite(statistic)
    statistic[~tested] = NO_TEST_STATISTIC
    finite = np.all(np.isfinite(position), axis=1)
    kept = np.flatnonzero(finite)
    tracks = np.zeros(len(kept), dtype=_SHADOW_TRACK_CDR)
    tracks['id'] = [int(reports[k].id) for k in kept.tolist()]
    tracks['status'] = status[kept]
    tracks['position'] = position[kept]
    tracks['position_covariance'] = covariance[kept]
    tracks['velocity'] = velocity[kept]
    tracks['velocity_covariance'] = velocity_covariance[kept]
    tracks['test_statistic'] = statistic[kept]
    tracks['test_dof'] = [int(reports[k].test_dof) if tested[k] else 0 for k in kept.tolist()]
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    name = frame_id.encode() + b'\0'
    head = struct.pack('<iII', sec, nanosec, len(name)) + name
    head += bytes(-len(head) % 4) + struct.pack('<I', len(kept))
    if len(kept):
        head += bytes(-len(head) % 8)
    body = tracks.tobytes()[:-4] if len(kept) else b''
    left_out = [int(reports[k].id) for k in np.flatnonzero(~finite).tolist()]
    return _CDR_LITTLE_ENDIAN + head + body, left_out


@dataclass(frozen=True)
class MarkerTypes:
    """The message classes the markers are built from (visualization_msgs/Marker,
    geometry_msgs/Point, std_msgs/ColorRGBA)."""

    marker: Callable[[], Any]
    point: Callable[..., Any]
    color: Callable[..., Any]


def _marker(
    types: MarkerTypes,
    namespace: str,
    marker_id: int,
    kind: str,
    status: int,
    scale: float,
    points: Sequence[Sequence[float]],
) -> Any:
    marker = types.marker()
    marker.ns = namespace
    marker.id = marker_id
    marker.type = getattr(marker, kind)
    marker.action = marker.ADD
    marker.pose.orientation.w = 1.0
    marker.scale.x = marker.scale.y = marker.scale.z = scale
    r, g, b = MARKER_COLOURS[status]
    marker.color = types.color(r=r, g=g, b=b, a=1.0)
    marker.points = [types.point(x=float(x), y=float(y), z=float(z)) for x, y, z in points]
    return marker


def fill_markers(
    tracks: Sequence[TrackReport],
    static_positions: Iterable[FloatArray],
    stamp_ns: int,
    frame_id: str,
    message: Any,
    types: MarkerTypes,
) -> Any:
    """Fill a visualization_msgs/MarkerArray and return it: a DELETEALL, then the held
    features with a known depth as spheres (pending red, dynamic green), the handed-over
    ``static_positions`` (blue spheres), and the recent trajectory of every dynamic feature
    as a green line strip (namespace ``dynamic_trajectories``, marker id = track id mod
    2^31). Non-finite points are left out; empty markers are not sent."""
    clear = types.marker()
    clear.action = clear.DELETEALL
    markers = [clear]
    by_status: dict[int, list[tuple[float, float, float]]] = {PENDING: [], DYNAMIC: []}
    for report in tracks:
        position = _finite_vector(report.position)
        if report.status in by_status and report.defined and position is not None:
            by_status[report.status].append(position)
    by_status[STATIC] = [
        point for point in (_finite_vector(p) for p in static_positions) if point is not None
    ]
    for status in (PENDING, STATIC, DYNAMIC):
        if by_status[status]:
            markers.append(
                _marker(
                    types, MARKER_NAMESPACES[status], 0, 'SPHERE_LIST', status, MARKER_SPHERE_M,
                    by_status[status],
                )
            )  # fmt: skip
    for report in tracks:
        trajectory = np.asarray(report.trajectory, dtype=np.float64).reshape(-1, 3)
        trajectory = trajectory[np.all(np.isfinite(trajectory), axis=1)]
        if report.status == DYNAMIC and len(trajectory) >= 2:
            markers.append(
                _marker(
                    types, TRAJECTORY_NAMESPACE, int(report.id) % 2**31, 'LINE_STRIP', DYNAMIC,
                    MARKER_LINE_M, trajectory.tolist(),
                )
            )  # fmt: skip
    for marker in markers:
        ns_to_stamp(stamp_ns, marker.header.stamp)
        marker.header.frame_id = frame_id
    message.markers = markers
    return message


def revoked_from_message(message: Any) -> list[int]:
    """Return the track ids of a slam_interfaces/ShadowTrackArray of features SLAM revoked
    (monoslam/revoked)."""
    return [int(track.id) for track in message.tracks]
