"""Messages <-> Shadow filter core types: the filter's input, ShadowTrackArray (messages or
CDR bytes) and RViz markers. No NaN leaves this module. Notes: docs/design/monoslam_nodes.md.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from monoslam_shadow_node.common.conversions import CDR_LITTLE_ENDIAN, MARKER_COLOURS
from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING, STATIC
from monoslam_shadow_node.common.core.inputs import CameraPose, Features
from monoslam_shadow_node.shadow_filter.core.shadow_filter import FrameInput, Handover, TrackReport
from slam_core.arrays import FloatArray
from slam_core.stamps import ns_to_stamp

UNKNOWN_COVARIANCE = (-1.0, *([0.0] * 8))
"""A 3x3 covariance with no estimate: element 0 is -1 (sensor_msgs convention)."""


NO_TEST_STATISTIC = -1.0
"""test_statistic of a feature that has not been tested yet (test_dof is then 0)."""


STATIC_MARKER_LIMIT = 5000
"""At most this many handed-over (static) features are drawn, the most recent ones."""


MARKER_SPHERE_M = 0.08


MARKER_LINE_M = 0.02


MARKER_NAMESPACES = {PENDING: 'pending', STATIC: 'static', DYNAMIC: 'dynamic'}


TRAJECTORY_NAMESPACE = 'dynamic_trajectories'


@dataclass(frozen=True)
class TrackFields:
    """The finite fields of one ShadowTrack: position (3) m, velocity (3) m/s, covariances (9)."""

    id: int
    status: int
    position: tuple[float, float, float]
    position_covariance: tuple[float, ...]
    velocity: tuple[float, float, float]
    velocity_covariance: tuple[float, ...]
    test_statistic: float
    test_dof: int


def frame_input(features: Features, pose: CameraPose) -> FrameInput:
    """Return the core's input for one image and its paired pose."""
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
    """Return a track's message fields with no NaN; None when its position is not finite."""
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
    """Return a handover's message fields (STATIC, zero velocity); None when not finite."""
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
    """Fill a ShadowTrackArray and return it; ``make_track`` makes an empty ShadowTrack."""
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
    """Return a frame's ShadowTrackArray as CDR bytes (``track_fields``' rules) and the ids
    left out (position not finite)."""
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
    # the rules of track_fields
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
    return CDR_LITTLE_ENDIAN + head + body, left_out


@dataclass(frozen=True)
class MarkerTypes:
    """The message classes of the markers: Marker, Point, ColorRGBA."""

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
    """Fill a MarkerArray and return it: DELETEALL, spheres (pending red, dynamic green,
    ``static_positions`` blue) and dynamic trajectories as green line strips."""
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
    """Return the track ids of a revoked ShadowTrackArray (monoslam/revoked)."""
    return [int(track.id) for track in message.tracks]
