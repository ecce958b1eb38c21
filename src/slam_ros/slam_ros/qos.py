"""QoS: rosbag2's recorded profiles <-> rclpy QoSProfile, and the suite's standard profiles."""

from __future__ import annotations

from collections.abc import Sequence

from rclpy.duration import Duration
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)

DEFAULT_DEPTH = 10
# Sensor inputs (images, camera_info) keep 0.5 s of a 30 Hz camera. On a busy machine a node's
# process may not run for a while: on 2 cores shared by a camera driver and four monocular
# nodes, single stalls of 70-290 ms were measured, and with the rclpy default of 5 (167 ms)
# they lost frames. A stall shorter than this delays frames instead; a node slower than its
# input on average still loses them, and /diagnostics counts them ('lost <input>'). A node
# that takes camera_info in step with reliable inputs (monoslam and shadow_filter: one per
# features message) keeps as many of it as of them, or it would lose camera_info first.
SENSOR_DEPTH = 15
# rosbag2 writes "infinite" durations as the largest (sec, nsec) it can represent.
_INFINITE_SEC = 0x7FFFFFFF

_RELIABILITY = {
    QosReliability.RELIABLE: ReliabilityPolicy.RELIABLE,
    QosReliability.BEST_EFFORT: ReliabilityPolicy.BEST_EFFORT,
}
_DURABILITY = {
    QosDurability.TRANSIENT_LOCAL: DurabilityPolicy.TRANSIENT_LOCAL,
    QosDurability.VOLATILE: DurabilityPolicy.VOLATILE,
}
_LIVELINESS = {
    QosLiveliness.AUTOMATIC: LivelinessPolicy.AUTOMATIC,
    QosLiveliness.MANUAL_BY_TOPIC: LivelinessPolicy.MANUAL_BY_TOPIC,
}


def matching_qos(offered: Sequence[QoSProfile], depth: int) -> QoSProfile:
    """A subscription QoS that receives from all ``offered``: reliable, latched only if all are."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE
        if offered and all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
        else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL
        if offered and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
        else DurabilityPolicy.VOLATILE,
    )


def sensor_qos(depth: int = SENSOR_DEPTH) -> QoSProfile:
    """Sensor inputs: best effort, volatile, keep last ``depth`` (default SENSOR_DEPTH)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
    )


def output_qos(depth: int = DEFAULT_DEPTH) -> QoSProfile:
    """Outputs: reliable, volatile, keep last ``depth``."""
    return QoSProfile(
        depth=depth, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE
    )


def latched_qos(depth: int = 1) -> QoSProfile:
    """Maps and landmark lists: reliable and transient-local, so late joiners get the latest."""
    return QoSProfile(
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def replayed_qos(depth: int) -> QoSProfile:
    """Inputs a restarted node must not miss: reliable, transient-local, keep last ``depth``."""
    return QoSProfile(
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def _duration(value: QosTime) -> Duration | None:
    if value.sec >= _INFINITE_SEC or (value.sec == 0 and value.nsec == 0):
        return None
    return Duration(seconds=value.sec, nanoseconds=value.nsec)


def profile_from_recorded(offered: Sequence[Qos], *, latched: bool = False) -> QoSProfile:
    """Return the publisher QoS to replay a topic with, from its recorded profiles."""
    if not offered:
        return QoSProfile(
            depth=DEFAULT_DEPTH,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
        )
    first = offered[0]
    agree = all(q.reliability == first.reliability for q in offered)
    all_latched = all(q.durability == QosDurability.TRANSIENT_LOCAL for q in offered)
    profile = QoSProfile(
        history=HistoryPolicy.KEEP_ALL
        if first.history == QosHistory.KEEP_ALL
        else HistoryPolicy.KEEP_LAST,
        depth=max(q.depth for q in offered) or DEFAULT_DEPTH,
        reliability=_RELIABILITY.get(first.reliability, ReliabilityPolicy.RELIABLE)
        if agree
        else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if all_latched else DurabilityPolicy.VOLATILE,
    )
    if (deadline := _duration(first.deadline)) is not None:
        profile.deadline = deadline
    if (lifespan := _duration(first.lifespan)) is not None:
        profile.lifespan = lifespan
    if first.liveliness in _LIVELINESS:
        profile.liveliness = _LIVELINESS[first.liveliness]
    if (lease := _duration(first.liveliness_lease_duration)) is not None:
        profile.liveliness_lease_duration = lease
    return profile


def _qos_time(duration: Duration) -> QosTime:
    nanoseconds = duration.nanoseconds
    if nanoseconds <= 0 or nanoseconds >= _INFINITE_SEC * 10**9:
        return QosTime(_INFINITE_SEC, 0xFFFFFFFF)
    return QosTime(nanoseconds // 10**9, nanoseconds % 10**9)


def recorded_from_profile(profile: QoSProfile) -> Qos:
    """Return the rosbag2 representation of an rclpy QoSProfile (for a recording's metadata)."""
    history = (
        QosHistory.KEEP_ALL if profile.history == HistoryPolicy.KEEP_ALL else QosHistory.KEEP_LAST
    )
    reliability = (
        QosReliability.BEST_EFFORT
        if profile.reliability == ReliabilityPolicy.BEST_EFFORT
        else QosReliability.RELIABLE
    )
    durability = (
        QosDurability.TRANSIENT_LOCAL
        if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        else QosDurability.VOLATILE
    )
    liveliness = (
        QosLiveliness.MANUAL_BY_TOPIC
        if profile.liveliness == LivelinessPolicy.MANUAL_BY_TOPIC
        else QosLiveliness.AUTOMATIC
    )
    return Qos(
        history=history,
        depth=profile.depth,
        reliability=reliability,
        durability=durability,
        deadline=_qos_time(profile.deadline),
        lifespan=_qos_time(profile.lifespan),
        liveliness=liveliness,
        liveliness_lease_duration=_qos_time(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=profile.avoid_ros_namespace_conventions,
    )
