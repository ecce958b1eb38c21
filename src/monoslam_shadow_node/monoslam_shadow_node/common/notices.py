"""What the processors tell their node to log, and the log throttle (ROS-free).

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

LEVELS = ('debug', 'info', 'warning', 'error')


@dataclass(frozen=True)
class Notice:
    """Something to log: kind, level (LEVELS), text, image stamp (int ns or None), throttle."""

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
    """Lets at most one throttled notice per kind through every ``period_s`` s."""

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
    """Log ``notice`` with an rclpy logger at its level, unless ``throttle`` holds it back."""
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
