"""builtin_interfaces/Time <-> int nanoseconds, for rclpy and rosbags messages alike."""

from __future__ import annotations

from typing import Any


def stamp_to_ns(stamp: Any) -> int:
    """Return a builtin_interfaces/Time as int nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(stamp_ns: int, stamp: Any) -> Any:
    """Fill a builtin_interfaces/Time message from int nanoseconds and return it."""
    stamp.sec, stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return stamp


def stamp_problem(stamp: Any) -> str | None:
    """Why a builtin_interfaces/Time is not a time (nanosec outside [0, 1e9)), or None."""
    nanosec = int(stamp.nanosec)
    if 0 <= nanosec < 1_000_000_000:
        return None
    return f'nanosec={nanosec} is outside [0, 1e9)'
