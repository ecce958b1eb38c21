"""Messages the mapper publishes, built from an EmResult (path, maps, markers like the
paper's Fig. 5, TF); see docs/design/em_sam_core.md."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
from builtin_interfaces.msg import Duration, Time
from geometry_msgs.msg import Point, PoseStamped, PoseWithCovarianceStamped, TransformStamped
from nav_msgs.msg import Path
from std_msgs.msg import ColorRGBA
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from em_sam_node.core.em_types import EmResult
from em_sam_node.core.sightings import Sightings
from em_sam_node.mapper.conversions import fill_yaw_quaternion
from slam_core.arrays import FloatArray
from slam_core.stamps import ns_to_stamp
from slam_interfaces.msg import (
    LandmarkEstimate,
    LandmarkMap,
    LandmarkSighting,
    MoveableLandmark,
    MoveableLandmarkArray,
)

RED = ColorRGBA(r=0.85, g=0.1, b=0.1, a=1.0)
GREEN = ColorRGBA(r=0.1, g=0.7, b=0.1, a=1.0)
BLUE = ColorRGBA(r=0.1, g=0.3, b=0.9, a=1.0)


def path_message(result: EmResult, stamps_ns: np.ndarray, frame: str, stamp: Time) -> Path:
    """Return the optimized keyframe trajectory as a nav_msgs/Path."""
    message = Path()
    message.header.frame_id = frame
    message.header.stamp = stamp
    for pose, stamp_ns in zip(result.poses, stamps_ns, strict=True):
        entry = PoseStamped()
        entry.header.frame_id = frame
        ns_to_stamp(int(stamp_ns), entry.header.stamp)
        entry.pose.position.x, entry.pose.position.y = float(pose[0]), float(pose[1])
        fill_yaw_quaternion(float(pose[2]), entry.pose.orientation)
        message.poses.append(entry)
    return message


def landmark_map_message(result: EmResult, frame: str, stamp: Time) -> LandmarkMap:
    """Return every landmark's estimate, weight and moveable flag as a LandmarkMap."""
    message = LandmarkMap()
    message.header.frame_id = frame
    message.header.stamp = stamp
    for index, landmark_id in enumerate(result.landmark_ids.tolist()):
        entry = LandmarkEstimate()
        entry.landmark_id = int(landmark_id)
        entry.position.x, entry.position.y = (float(v) for v in result.positions[index])
        entry.covariance = [float(v) for v in result.covariances[index].reshape(4)]
        entry.weight = float(result.weights[index])
        entry.moveable = bool(result.moveable[index])
        entry.num_observations = int(result.num_observations[index])
        message.landmarks.append(entry)
    return message


def sighting_messages(sightings: Sightings) -> list[LandmarkSighting]:
    """Return LandmarkSighting messages, in the given (most recent first) order."""
    messages = []
    for stamp_ns, position, covariance in zip(
        sightings.stamps_ns, sightings.positions, sightings.covariances, strict=True
    ):
        entry = LandmarkSighting()
        ns_to_stamp(int(stamp_ns), entry.stamp)
        entry.position.x, entry.position.y = float(position[0]), float(position[1])
        entry.covariance = [float(v) for v in covariance.reshape(4)]
        messages.append(entry)
    return messages


def moveable_message(result: EmResult, frame: str, stamp: Time) -> MoveableLandmarkArray:
    """Return the moveable landmarks with all their sightings, most recent first."""
    message = MoveableLandmarkArray()
    message.header.frame_id = frame
    message.header.stamp = stamp
    for index in np.flatnonzero(result.moveable):
        landmark_id = int(result.landmark_ids[index])
        entry = MoveableLandmark()
        entry.landmark_id = landmark_id
        entry.weight = float(result.weights[index])
        entry.sightings = sighting_messages(result.sightings[landmark_id])
        message.landmarks.append(entry)
    return message


def _marker(
    namespace: str,
    marker_id: int,
    kind: int,
    frame: str,
    stamp: Time,
    color: ColorRGBA,
    scale: float,
) -> Marker:
    marker = Marker()
    marker.header.frame_id = frame
    marker.header.stamp = stamp
    marker.ns = namespace
    marker.id = marker_id
    marker.type = kind
    marker.action = Marker.ADD
    marker.pose.orientation.w = 1.0
    marker.scale.x = marker.scale.y = marker.scale.z = scale
    marker.color = color
    marker.lifetime = Duration()
    return marker


def _points(xy: FloatArray) -> list[Point]:
    return [Point(x=float(x), y=float(y), z=0.0) for x, y in xy]


def markers_message(result: EmResult, frame: str, stamp: Time) -> MarkerArray:
    """Return the Fig. 5 style MarkerArray (replaces everything previously drawn)."""
    clear = Marker()
    clear.action = Marker.DELETEALL
    markers: list[Any] = [clear]
    trajectory = _marker('trajectory', 0, Marker.LINE_STRIP, frame, stamp, RED, 0.03)
    trajectory.points = _points(result.poses[:, :2])
    markers.append(trajectory)
    static = _marker('static_landmarks', 0, Marker.SPHERE_LIST, frame, stamp, GREEN, 0.2)
    static.points = _points(result.positions[~result.moveable])
    markers.append(static)
    for index in np.flatnonzero(result.moveable).tolist():
        moveable_id = int(result.landmark_ids[index])
        history = result.sightings[moveable_id].positions[::-1]  # oldest first
        points = _marker(
            'moveable_sightings', moveable_id, Marker.SPHERE_LIST, frame, stamp, BLUE, 0.12
        )
        points.points = _points(history)
        markers.append(points)
        dotted = _marker(
            'moveable_history', moveable_id, Marker.LINE_LIST, frame, stamp, BLUE, 0.02
        )
        dotted.points = _points(_dotted_segments(history))
        markers.append(dotted)
    for index, landmark_id in enumerate(result.landmark_ids.tolist()):
        label = _marker(
            'labels',
            int(landmark_id),
            Marker.TEXT_VIEW_FACING,
            frame,
            stamp,
            BLUE if result.moveable[index] else GREEN,
            0.2,
        )
        label.pose.position.x, label.pose.position.y = (float(v) for v in result.positions[index])
        label.pose.position.z = 0.3
        label.text = str(landmark_id)
        markers.append(label)
    message = MarkerArray()
    message.markers = markers
    return message


def _dotted_segments(points: FloatArray, dash_m: float = 0.1) -> FloatArray:
    """Return LINE_LIST endpoints (2n,2) drawing a dotted polyline through ``points``."""
    segments = []
    for start, end in itertools.pairwise(points):
        length = float(np.hypot(*(end - start)))
        count = max(int(length / (2 * dash_m)), 1)
        for k in range(count):
            a = start + (end - start) * (2 * k) / (2 * count)
            b = start + (end - start) * (2 * k + 1) / (2 * count)
            segments.extend([a, b])
    return np.array(segments).reshape(-1, 2)


def map_to_odom_tf(
    transform: FloatArray, map_frame: str, odom_frame: str, stamp: Time
) -> TFMessage:
    """Return a TFMessage with the map->odom transform (x m, y m, theta rad)."""
    message = TransformStamped()
    message.header.frame_id = map_frame
    message.header.stamp = stamp
    message.child_frame_id = odom_frame
    message.transform.translation.x = float(transform[0])
    message.transform.translation.y = float(transform[1])
    fill_yaw_quaternion(float(transform[2]), message.transform.rotation)
    return TFMessage(transforms=[message])


def pose_message(
    stamp_ns: int, pose: FloatArray, covariance: FloatArray, frame: str
) -> PoseWithCovarianceStamped:
    """The robot's pose (x, y, theta) and covariance (3, 3) as ROS's 6 x 6 (z, roll, pitch 0)."""
    message = PoseWithCovarianceStamped()
    message.header.frame_id = frame
    ns_to_stamp(int(stamp_ns), message.header.stamp)
    message.pose.pose.position.x, message.pose.pose.position.y = float(pose[0]), float(pose[1])
    fill_yaw_quaternion(float(pose[2]), message.pose.pose.orientation)
    full = np.zeros((6, 6))
    planar = [0, 1, 5]
    full[np.ix_(planar, planar)] = covariance
    message.pose.covariance = full.ravel().tolist()
    return message
