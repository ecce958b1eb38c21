"""Whether a node's inputs stopped, judged on its timer ticks (wall clock, ROS-free).

Design notes: docs/design/ros_and_core.md ("Idle inputs").
"""

from __future__ import annotations

import time
from collections.abc import Callable

MIN_TICK_S = 0.05


class IdleWatch:
    """Idle once no input came for ``idle_s`` s, seen on two ticks in a row.

    ``note_input()`` at every input taken, ``idle()`` on a timer every ``tick_s`` s; a tick
    more than two periods after the one before (the node was busy) does not count.
    ``clock`` returns seconds (default: ``time.monotonic``).
    """

    def __init__(self, idle_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        if not idle_s > 0:
            raise ValueError(f'idle_s={idle_s}: must be > 0')
        self.idle_s = idle_s
        self._clock = clock
        self._last_input = clock()
        self._last_tick: float | None = None
        self._armed = False

    @property
    def tick_s(self) -> float:
        """The timer period to call ``idle()`` at, s."""
        return max(self.idle_s / 2, MIN_TICK_S)

    @property
    def since_input_s(self) -> float:
        """Seconds since the last input (or since the watch was made)."""
        return self._clock() - self._last_input

    def note_input(self) -> None:
        """An input was taken now."""
        self._last_input = self._clock()
        self._armed = False

    def idle(self) -> bool:
        """Call on each tick: whether the inputs stopped."""
        now = self._clock()
        blocked = self._last_tick is not None and now - self._last_tick > 2 * self.tick_s
        self._last_tick = now
        if now - self._last_input <= self.idle_s or blocked:
            self._armed = False  # not idle, or the node was too busy to take what waited
            return False
        if not self._armed:
            self._armed = True  # the inputs queued meanwhile are taken before the next tick
            return False
        return True
