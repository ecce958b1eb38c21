"""Messages <-> MonoSLAM core types (fiducials, handovers, depth, poses, map, predictions).

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from monoslam_shadow_node.common.conversions import (
    CDR_ERRORS,
    FEATURE_TRACK_CDR,
    deserialized,
    feature_array_cdr,
    tracks_cdr,
)
from monoslam_shadow_node.monoslam.core.monoslam_types import MapPoint, MonoSlamResult
from monoslam_shadow_node.monoslam.known_points_input import DepthImage
from monoslam_shadow_node.monoslam.settings import TARGET_CORNERS
from slam_core.arrays import FloatArray, IntArray
from slam_core.stamps import ns_to_stamp, stamp_to_ns

FLOAT32, FLOAT64, UINT8 = 7, 8, 2
"""sensor_msgs/PointField datatype constants."""
POINT_FIELDS = (
    ('x', 0, FLOAT32),
    ('y', 4, FLOAT32),
    ('z', 8, FLOAT32),
    ('sigma_m', 12, FLOAT32),
    ('id', 16, FLOAT64),
    ('active', 24, UINT8),
    ('handover', 25, UINT8),
)
"""One point of monoslam/map: (name, byte offset, datatype). Position (m), the largest
standard deviation (m), track id (float64: PointField has no int64; exact up to 2^53), in the
filter (1) or retired (0), entered by a handover (1) or as a new feature (0)."""
_FORMATS = {FLOAT32: '<f4', FLOAT64: '<f8', UINT8: 'u1'}
POINT_DTYPE = np.dtype(
    {
        'names': [name for name, _, _ in POINT_FIELDS],
        'formats': [_FORMATS[datatype] for _, _, datatype in POINT_FIELDS],
        'offsets': [offset for _, offset, _ in POINT_FIELDS],
        'itemsize': 32,
    }
)


@dataclass(frozen=True, eq=False)
class TargetSighting:
    """A FiducialArray reduced to the target: stamp (int ns), frame, corners (4, 2) px or None."""

    stamp_ns: int
    frame_id: str
    corners_px: FloatArray | None
    detected: tuple[tuple[str, int], ...]
    problem: str | None = None

    def describe_detected(self) -> str:
        """Return 'no marker detected' or 'detected: DICT_5X5_50 id 3, ...' for the log."""
        if not self.detected:
            return 'no marker detected'
        return 'detected: ' + ', '.join(f'{d} id {i}' for d, i in self.detected)


@dataclass(frozen=True, eq=False)
class HandoverInput:
    """One handover: id, status, position (3,) m, covariance (3, 3) m^2 (may hold NaN)."""

    id: int
    status: int
    position: FloatArray
    covariance: FloatArray


@dataclass(frozen=True)
class PoseFields:
    """One pose's finite numbers: stamp (int ns), centre (3) m, quaternion (x, y, z, w), covariance
    (36) and cross-covariances (36 each) with the poses stamped ``cross_stamps``."""

    stamp_ns: int
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    covariance: tuple[float, ...]
    cross_stamps: tuple[int, ...] = ()
    cross_covariances: tuple[float, ...] = ()

    @property
    def sigmas(self) -> tuple[float, float]:
        """Largest position (m) and rotation (rad) standard deviation."""
        variances = np.diagonal(np.reshape(self.covariance, (6, 6)))
        sigma = np.sqrt(np.maximum(variances, 0.0))
        return float(sigma[:3].max()), float(sigma[3:].max())

    def describe(self) -> str:
        """Return 'camera at (x, y, z) m, sigma 0.02 m / 0.004 rad' for the log."""
        x, y, z = self.position
        position_sigma, rotation_sigma = self.sigmas
        return (
            f'camera at ({x:.3f}, {y:.3f}, {z:.3f}) m, sigma {position_sigma:.3f} m / '
            f'{rotation_sigma:.4f} rad'
        )


def target_from_fiducials(message: Any, marker_id: int, dictionary: str) -> TargetSighting:
    """Return the target's corners in a FiducialArray (its best detection, or why none is used)."""
    detections = list(message.detections)
    detected = tuple((str(d.dictionary), int(d.id)) for d in detections)
    stamp_ns, frame_id = stamp_to_ns(message.header.stamp), str(message.header.frame_id)
    target = [d for d in detections if int(d.id) == marker_id and d.dictionary == dictionary]
    if not target:
        return TargetSighting(stamp_ns, frame_id, None, detected)
    best = min(target, key=lambda d: float(d.reprojection_error_px))
    corners = np.asarray(best.corners_px, dtype=np.float64)
    if corners.size != 2 * TARGET_CORNERS or not np.all(np.isfinite(corners)):
        problem = f'target corners {corners.tolist()} are not {TARGET_CORNERS} finite pixels'
        return TargetSighting(stamp_ns, frame_id, None, detected, problem)
    return TargetSighting(stamp_ns, frame_id, corners.reshape(TARGET_CORNERS, 2), detected)


def depth_from_image(message: Any) -> DepthImage:
    """Return a REP 118 depth Image (16UC1 mm or 32FC1 m) in m; ValueError naming the problem."""
    encoding = str(message.encoding)
    kinds: dict[str, np.dtype[Any]] = {
        '16UC1': np.dtype('<u2'), 'mono16': np.dtype('<u2'), '32FC1': np.dtype('<f4')
    }  # fmt: skip
    if encoding not in kinds:
        raise ValueError(f'depth image encoding {encoding!r}: expected 16UC1 (mm) or 32FC1 (m)')
    dtype = kinds[encoding].newbyteorder('>' if message.is_bigendian else '<')
    height, width, step = int(message.height), int(message.width), int(message.step)
    data = np.frombuffer(bytes(message.data), dtype=np.uint8)
    if height < 1 or width < 1 or step < width * dtype.itemsize or len(data) < height * step:
        raise ValueError(
            f'depth image {width}x{height} px, step {step}: {len(data)} bytes do not hold it'
        )
    rows = data[: height * step].reshape(height, step)[:, : width * dtype.itemsize]
    depth = rows.copy().view(dtype).reshape(height, width).astype(np.float64)
    if dtype.kind == 'u':
        depth = np.where(depth > 0, depth * 1e-3, np.nan)
    stamp = stamp_to_ns(message.header.stamp)
    return DepthImage(stamp, str(message.header.frame_id), depth)


def dynamic_ids(message: Any) -> list[int]:
    """Return the ids of the DYNAMIC tracks of a slam_interfaces/ShadowTrackArray."""
    return [int(track.id) for track in message.tracks if int(track.status) == DYNAMIC_STATUS]


SHADOW_TRACK_CDR = np.dtype(
    {'names': ['id', 'status'], 'formats': ['<i8', 'u1'], 'offsets': [0, 8], 'itemsize': 220}
)
"""A slam_interfaces/ShadowTrack in little-endian CDR, its id and status read (220 bytes: the
last one in a sequence has no padding after it)."""
SHADOW_TRACK_STRIDE = 224
"""Bytes from one ShadowTrack to the next in a sequence: id 8, status 1 (+7 to align), position
and velocity 24 each, their covariances 72 each, test statistic 8, its dof 4 (+4 to align the
next id)."""


def dynamic_ids_from_cdr(data: bytes, deserialize: Callable[[bytes], Any]) -> list[int]:
    """Return ``dynamic_ids`` of a serialized ShadowTrackArray; ValueError when it is none."""
    try:
        _, _, tracks = tracks_cdr(data, SHADOW_TRACK_CDR, SHADOW_TRACK_STRIDE)
    except CDR_ERRORS:
        return dynamic_ids(deserialized(data, deserialize, 'shadow tracks'))
    return tracks['id'][tracks['status'] == DYNAMIC_STATUS].astype(np.int64).tolist()


def handovers_from_message(message: Any) -> list[HandoverInput]:
    """Return the handovers of a slam_interfaces/ShadowTrackArray (shadow/static_features)."""
    return [
        HandoverInput(
            int(track.id),
            int(track.status),
            np.array([float(track.position.x), float(track.position.y), float(track.position.z)]),
            np.asarray(track.position_covariance, dtype=np.float64).reshape(3, 3),
        )
        for track in message.tracks
    ]


def pose_fields(result: MonoSlamResult) -> PoseFields | None:
    """Return a result's pose as finite numbers, None while none or when not finite."""
    if result.rotation is None or result.centre is None or result.pose_covariance is None:
        return None
    arrays = (result.rotation, result.centre, result.pose_covariance)
    if not all(np.all(np.isfinite(a)) for a in arrays):
        return None
    x, y, z, w = Rotation.from_matrix(result.rotation).as_quat()
    cx, cy, cz = (float(v) for v in result.centre)
    covariance = np.asarray(result.pose_covariance, dtype=np.float64).reshape(36)
    cross, stamps = result.pose_cross_covariances, tuple(result.pose_cross_stamps)
    if cross is None or not stamps or not np.all(np.isfinite(cross)):
        cross, stamps = np.zeros(0), ()
    return PoseFields(
        result.stamp_ns, (cx, cy, cz), (float(x), float(y), float(z), float(w)),
        tuple(float(v) for v in covariance), stamps, tuple(np.ravel(cross).tolist()),
    )  # fmt: skip


def _fill_pose(fields: PoseFields, pose: Any) -> Any:
    pose.position.x, pose.position.y, pose.position.z = fields.position
    q = pose.orientation
    q.x, q.y, q.z, q.w = fields.orientation
    return pose


def fill_pose_with_covariance(fields: PoseFields, frame_id: str, message: Any) -> Any:
    """Fill a geometry_msgs/PoseWithCovarianceStamped and return it."""
    ns_to_stamp(fields.stamp_ns, message.header.stamp)
    message.header.frame_id = frame_id
    _fill_pose(fields, message.pose.pose)
    message.pose.covariance = list(fields.covariance)
    return message


def fill_pose_stamped(fields: PoseFields, frame_id: str, message: Any) -> Any:
    """Fill a geometry_msgs/PoseStamped (a monoslam/path entry) and return it."""
    ns_to_stamp(fields.stamp_ns, message.header.stamp)
    message.header.frame_id = frame_id
    _fill_pose(fields, message.pose)
    return message


def fill_transform(fields: PoseFields, parent: str, child: str, message: Any) -> Any:
    """Fill a geometry_msgs/TransformStamped parent -> child and return it."""
    ns_to_stamp(fields.stamp_ns, message.header.stamp)
    message.header.frame_id = parent
    message.child_frame_id = child
    translation = message.transform.translation
    translation.x, translation.y, translation.z = fields.position
    rotation = message.transform.rotation
    rotation.x, rotation.y, rotation.z, rotation.w = fields.orientation
    return message


def cloud_points(points: Iterable[MapPoint]) -> np.ndarray:
    """Return the map points with a defined, finite position as a ``POINT_DTYPE`` array."""
    rows = []
    for point in points:
        if point.covariance is None or not np.all(np.isfinite(point.position)):
            continue
        covariance = 0.5 * (point.covariance + point.covariance.T)
        if not np.all(np.isfinite(covariance)):
            continue
        sigma = math.sqrt(max(float(np.max(np.linalg.eigvalsh(covariance))), 0.0))
        x, y, z = (float(v) for v in point.position)
        rows.append((x, y, z, sigma, float(point.id), point.active, point.source == 'handover'))
    return np.array(rows, dtype=POINT_DTYPE)


def fill_cloud(
    points: np.ndarray, stamp_ns: int, frame_id: str, message: Any, make_field: Callable[..., Any]
) -> Any:
    """Fill a PointCloud2 with ``POINT_DTYPE`` points (``make_field``: PointField); return it."""
    ns_to_stamp(stamp_ns, message.header.stamp)
    message.header.frame_id = frame_id
    message.height, message.width = 1, len(points)
    message.fields = [
        make_field(name=name, offset=offset, datatype=datatype, count=1)
        for name, offset, datatype in POINT_FIELDS
    ]
    message.is_bigendian = False
    message.point_step = POINT_DTYPE.itemsize
    message.row_step = POINT_DTYPE.itemsize * len(points)
    message.data = points.tobytes()
    message.is_dense = True
    return message


def prediction_rows(
    pixels: FloatArray, covariances: FloatArray | None, warps: FloatArray | None
) -> tuple[FloatArray, FloatArray, FloatArray, np.ndarray]:
    """Return pixels (M, 2), covariance rows (M, 3), warp rows (M, 4) and finite mask (M,)."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if covariances is None:
        upper = np.zeros((len(pixels), 3))
    else:
        full = np.asarray(covariances, dtype=np.float64).reshape(-1, 2, 2)
        upper = np.column_stack([full[:, 0, 0], full[:, 0, 1], full[:, 1, 1]])
        upper[~np.all(np.isfinite(upper), axis=1)] = 0.0
    flat = np.zeros((len(pixels), 4))
    if warps is not None:
        flat = np.asarray(warps, dtype=np.float64).reshape(-1, 4).copy()
        flat[~np.all(np.isfinite(flat), axis=1)] = 0.0
    return pixels, upper, flat, np.all(np.isfinite(pixels), axis=1)


def fill_predictions(
    ids: IntArray,
    pixels: FloatArray,
    stamp_ns: int,
    frame_id: str,
    message: Any,
    make_track: Callable[..., Any],
    covariances: FloatArray | None = None,
    warps: FloatArray | None = None,
) -> Any:
    """Fill a FeatureTrackArray with predicted pixels (M, 2), covariances, warps (M, 2, 2)."""
    ns_to_stamp(stamp_ns, message.header.stamp)
    message.header.frame_id = frame_id
    pixels, upper, flat, finite = prediction_rows(pixels, covariances, warps)
    # the rows go in as float64 arrays made for this message: a message takes an array as it
    # is, where a list is checked and converted number by number
    message.tracks = [
        make_track(id=i, u=u, v=v, covariance=cov, warp=warp)
        for i, (u, v), cov, warp in zip(
            np.asarray(ids)[finite].tolist(), pixels[finite].tolist(),
            np.array(upper[finite]), np.array(flat[finite]), strict=True,
        )
    ]  # fmt: skip
    return message


def predictions_cdr(
    ids: IntArray,
    pixels: FloatArray,
    stamp_ns: int,
    frame_id: str,
    covariances: FloatArray | None = None,
    warps: FloatArray | None = None,
) -> bytes:
    """Return ``fill_predictions``'s FeatureTrackArray as little-endian CDR bytes."""
    pixels, upper, flat, finite = prediction_rows(pixels, covariances, warps)
    tracks = np.zeros(int(np.count_nonzero(finite)), FEATURE_TRACK_CDR)
    tracks['id'] = np.asarray(ids, dtype=np.int64)[finite]
    tracks['u'], tracks['v'] = pixels[finite, 0], pixels[finite, 1]
    tracks['covariance'], tracks['warp'] = upper[finite], flat[finite]
    return feature_array_cdr(tracks, stamp_ns, frame_id)


DYNAMIC_STATUS = 2
"""slam_interfaces/ShadowTrack.DYNAMIC."""


def revoked_ids(result: MonoSlamResult) -> list[int]:
    """Return the features the frame revoked (handed over, then found moving)."""
    return [int(i) for i, why in result.removed.items() if why == 'revoked']


def fill_revoked(
    ids: Sequence[int], stamp_ns: int, frame_id: str, message: Any, make_track: Callable[..., Any]
) -> Any:
    """Fill a ShadowTrackArray with revoked features (DYNAMIC, no position) and return it."""
    ns_to_stamp(stamp_ns, message.header.stamp)
    message.header.frame_id = frame_id
    unknown = [-1.0] + [0.0] * 8
    fields = {'status': DYNAMIC_STATUS, 'test_statistic': -1.0}
    message.tracks = [
        make_track(id=int(i), position_covariance=unknown, velocity_covariance=unknown, **fields)
        for i in ids
    ]
    return message


def tum_text(poses: Sequence[PoseFields]) -> str:
    """Return a trajectory in the TUM format: one line 'stamp_s x y z qx qy qz qw' per pose."""
    lines = [
        f'{p.stamp_ns // 10**9}.{p.stamp_ns % 10**9:09d} '
        + ' '.join(f'{v:.9f}' for v in (*p.position, *p.orientation))
        for p in poses
    ]
    return ''.join(f'{line}\n' for line in lines)
