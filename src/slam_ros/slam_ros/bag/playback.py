"""ROS-free playback: bag-to-wall time, prefetching, lateness (docs/design/ros_and_core.md)."""

from __future__ import annotations

import collections
import statistics
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import cast

from slam_ros.bag.source import BagMessage, BagSource


@dataclass(frozen=True)
class PlaybackConfig:
    """Validated player settings. Times are float seconds; rate is a speed factor."""

    bag_path: Path
    rate: float = 1.0
    start_offset_s: float = 0.0
    topics: tuple[str, ...] = ()
    remaps: dict[str, str] = field(default_factory=dict)
    loop: bool = False
    clock_hz: float = 100.0
    wait_for_subscribers_s: float = 0.0
    progress_period_s: float = 5.0


@dataclass(frozen=True)
class TimeMapping:
    """Maps bag stamps (int ns) to monotonic wall deadlines (int ns) at a rate factor."""

    bag_start_ns: int
    wall_start_ns: int
    rate: float

    def wall_deadline_ns(self, bag_ns: int) -> int:
        """Return the monotonic time at which the message stamped ``bag_ns`` is due."""
        return self.wall_start_ns + round((bag_ns - self.bag_start_ns) / self.rate)

    def bag_time_ns(self, wall_ns: int) -> int:
        """Return the bag time corresponding to monotonic time ``wall_ns``."""
        return self.bag_start_ns + round((wall_ns - self.wall_start_ns) * self.rate)


@dataclass
class LatenessStats:
    """Publish lateness (actual minus scheduled wall time) of every message, int ns."""

    samples_ns: list[int] = field(default_factory=list)

    def add(self, lateness_ns: int) -> None:
        """Record one message's lateness."""
        self.samples_ns.append(lateness_ns)

    def summary_ms(self) -> dict[str, float]:
        """Return count, median, p95 and max lateness in milliseconds."""
        if not self.samples_ns:
            return {
                'count': 0,
                'median_ms': float('nan'),
                'p95_ms': float('nan'),
                'max_ms': float('nan'),
            }
        ordered = sorted(self.samples_ns)
        p95 = ordered[min(len(ordered) - 1, int(0.95 * len(ordered)))]
        return {
            'count': len(ordered),
            'median_ms': statistics.median(ordered) / 1e6,
            'p95_ms': p95 / 1e6,
            'max_ms': ordered[-1] / 1e6,
        }


_END = object()
DEFAULT_PREFETCH_BYTES = 64 * 2**20


class Prefetcher:
    """Reads a bag in a background thread into a buffer of at most ``max_bytes``."""

    def __init__(
        self,
        source: BagSource,
        topics: tuple[str, ...] | None,
        start_ns: int | None,
        *,
        max_bytes: int = DEFAULT_PREFETCH_BYTES,
    ) -> None:
        self.max_bytes = max_bytes
        self._items: collections.deque[object] = collections.deque()
        self._bytes = 0
        self._condition = threading.Condition()
        self._primed = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(source, topics, start_ns), name='bag-prefetch', daemon=True
        )
        self._thread.start()

    def _run(
        self, source: BagSource, topics: tuple[str, ...] | None, start_ns: int | None
    ) -> None:
        try:
            for message in source.messages(topics, start_ns=start_ns, validate=True):
                with self._condition:
                    while self._bytes >= self.max_bytes and not self._stop.is_set():
                        self._primed.set()
                        self._condition.wait(0.1)
                    if self._stop.is_set():
                        return
                    self._items.append(message)
                    self._bytes += len(message.data)
                    self._condition.notify_all()
            self._finish(_END)
        except BaseException as err:  # handed to the consumer, which re-raises it
            self._finish(err)

    def _finish(self, item: object) -> None:
        with self._condition:
            self._items.append(item)
            self._primed.set()
            self._condition.notify_all()

    def wait_primed(self, timeout_s: float) -> bool:
        """Block until the buffer is full or the bag is read (or timeout); True if primed."""
        return self._primed.wait(timeout_s)

    def __iter__(self) -> Iterator[BagMessage]:
        while True:
            with self._condition:
                while not self._items:
                    self._condition.wait()
                item = self._items.popleft()
                if isinstance(item, BagMessage):
                    self._bytes -= len(item.data)
                    self._condition.notify_all()
            if item is _END:
                return
            if isinstance(item, BaseException):
                raise item
            yield cast(BagMessage, item)

    def close(self) -> None:
        """Stop the reader thread and wait for it."""
        self._stop.set()
        with self._condition:
            self._condition.notify_all()
        self._thread.join(timeout=5.0)
