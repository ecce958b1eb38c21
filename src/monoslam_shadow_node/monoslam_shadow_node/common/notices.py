"""What the processors of monoslam, shadow_filter and feature_tracker tell their node to log
(ROS-free).

A processor returns ``Notice`` outcomes next to its results; the node logs each at its level
and does nothing else with it. A notice of a steady state (waiting for the camera, for the
target, for a pose that never comes) is marked ``throttle``: the node logs at most one per
kind every ``LogThrottle.period_s`` seconds, so that a kind does not silence another.
``log_notice`` does that with a node's logger.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

LEVELS = ('debug', 'info', 'warning', 'error')


@dataclass(frozen=True)
class Notice:
    """Something to log: its kind (e.g. 'dropped', 'pose_covariance', 'skipped', 'started'), its
    level (one of LEVELS), the line to log, the image stamp it concerns (int ns, None for
    none) and whether it repeats a steady state (log it throttled, per kind)."""

    kind: str
    level: str
    text: str
    stamp_ns: int | None = None
    throttle: bool = False

    def __post_init__(self) -> None:
        if self.level not in LEVELS:
            raise ValueError(f'notice level {self.level!r}: must be one of {", ".join(LEVELS)}')

    def __str__(self) -> str:
        return self.text


@dataclass
class LogThrottle:
    """Decides whether a throttled notice is logged now: at most one per kind every
    ``period_s`` seconds of the caller's monotonic clock (``now_s``)."""

    period_s: float
    _last_s: dict[str, float] = field(default_factory=dict)

    def allows(self, notice: Notice, now_s: float) -> bool:
        """Return True when ``notice`` should be logged at ``now_s`` (s); remember it."""
        if not notice.throttle:
            return True
        last_s = self._last_s.get(notice.kind)
        if last_s is not None and now_s - last_s < self.period_s:
            return False
        self._last_s[notice.kind] = now_s
        return True


def log_notice(logger: Any, notice: Notice, throttle: LogThrottle, now_s: float) -> None:
    """Log ``notice`` with a node's logger (rclpy's ``RcutilsLogger``) at its level, unless
    ``throttle`` holds it back at ``now_s`` (monotonic s). One call site per level: rclpy
    refuses a call site whose severity changes between calls."""
    if not throttle.allows(notice, now_s):
        return
    if notice.level == 'error':
        logger.error(notice.text)
    elif notice.level == 'warning':
        logger.warning(notice.text)
    elif notice.level == 'info':
        logger.info(notice.text)
    else:
        logger.debug(notice.text)
