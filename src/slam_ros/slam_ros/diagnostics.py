"""Per-node /diagnostics: losses, processing time, lag (docs/design/ros_and_core.md)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from slam_core.stamps import stamp_to_ns
from slam_ros.progress import Progress, paced
from slam_ros.qos import output_qos

BUSY_WARN = 0.9
"""Busy above this share of the wall time, a node cannot keep up with a higher input rate."""
IDLE_KEY = 'idle s'
"""The value with the seconds since the node last took an input."""
LOST_TEXT = 'messages before taking them'
"""What a node logs after 'lost N' when its queues lost inputs (tests search for it)."""
OK_AGAIN_REPORTS = 5
"""Reports in a row without a problem before the log says the node is OK again."""


class Diagnostics:
    """A node's /diagnostics publisher; ``log(level, text)`` gets its state changes."""

    def __init__(
        self,
        node: Node,
        counts: Callable[[], Mapping[str, int]],
        period_s: float = 1.0,
        *,
        values: Callable[[], Mapping[str, str]] | None = None,
        log: Callable[[str, str], None] | None = None,
    ) -> None:
        self.node, self.counts, self.values = node, counts, values
        self._log = log or self._node_log
        self._warned: set[str] = set()  # kinds of problem logged and not yet OK again
        self._ok_reports = 0
        self.received: dict[str, int] = {}
        self.lost: dict[str, int] = {}
        self.unknown_lost: set[str] = set()
        self._sequence: dict[str, int] = {}  # per input, the last sequence number taken
        self.first_sequence: dict[str, int] = {}  # per input, the first one taken
        self.gap_wait_ms: dict[str, float] = {}  # per input, the queue wait after its last gap
        self._window_wait_ms = 0.0
        self._last_lost = 0
        self.processing_s = 0.0
        self.latest_stamp_ns: int | None = None
        self.last_input_s = time.monotonic()  # when an input callback last ended
        self.active = 0  # callbacks running now
        self._window_s = self._window_max_s = 0.0
        self._window_start = time.perf_counter()
        self._last_dropped = 0
        self.failed_takes = 0  # messages rclpy failed to take (slam_ros.spin), lost
        self._last_failed_takes = 0
        self.publisher = node.create_publisher(DiagnosticArray, '/diagnostics', output_qos())
        node.create_timer(period_s, self.publish, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._subscriptions_seen = -1
        self._inputs_by_topic: dict[str, list[str]] = {}
        # paced replay: a progress report after every callback (slam_ros.progress)
        self.progress = Progress(node, self.taken_by_topic) if paced() else None

    def timed(
        self, callback: Callable[..., None], input: str | None = None
    ) -> Callable[..., None]:
        """Return ``callback`` timed; with ``input``, a subscription callback counted on it."""
        if input is None:

            def timer_wrapper() -> None:
                start = time.perf_counter()
                self.active += 1
                try:
                    callback()
                finally:
                    self.active -= 1
                    self._add_time(time.perf_counter() - start)
                    if self.progress is not None:
                        self.progress.report()

            return timer_wrapper
        self.received.setdefault(input, 0)
        self.lost.setdefault(input, 0)

        def wrapper(message: Any, info: Mapping[str, Any]) -> None:
            self.received[input] += 1
            wait_ms = math.nan
            received_ns = info.get('received_timestamp')
            if received_ns:  # system clock, as rmw stamps it
                wait_ms = max(0.0, (time.time_ns() - received_ns) / 1e6)
                self._window_wait_ms = max(self._window_wait_ms, wait_ms)
            self._count_lost(input, info.get('publication_sequence_number'), wait_ms)
            start = time.perf_counter()
            self.active += 1
            try:
                callback(message)
            finally:
                self.active -= 1
                self.last_input_s = time.monotonic()
                self._add_time(time.perf_counter() - start)
                header = getattr(message, 'header', None)
                if header is not None:
                    stamp_ns = stamp_to_ns(header.stamp)
                    if self.latest_stamp_ns is None or stamp_ns > self.latest_stamp_ns:
                        self.latest_stamp_ns = stamp_ns
                if self.progress is not None:
                    self.progress.report()

        wrapper.slam_input = input  # type: ignore[attr-defined]
        return wrapper

    def taken_by_topic(self) -> dict[str, int]:
        """Messages taken per subscribed topic (resolved name), over the inputs on it."""
        subscriptions = list(self.node.subscriptions)
        if len(subscriptions) != self._subscriptions_seen:  # the inputs on each topic, once
            self._subscriptions_seen = len(subscriptions)
            self._inputs_by_topic = {}
            for subscription in subscriptions:
                input = getattr(subscription.callback, 'slam_input', None)
                if input is not None:
                    inputs = self._inputs_by_topic.setdefault(subscription.topic_name, [])
                    inputs.append(input)
        return {
            topic: sum(self.received[input] for input in inputs)
            for topic, inputs in self._inputs_by_topic.items()
        }

    def _add_time(self, spent: float) -> None:
        self.processing_s += spent
        self._window_s += spent
        self._window_max_s = max(self._window_max_s, spent)

    def _count_lost(self, input: str, sequence: int | None, wait_ms: float) -> None:
        """Count the gap in the publisher's sequence numbers before ``sequence`` as lost."""
        if sequence is None or input in self.unknown_lost:
            return
        last = self._sequence.get(input)
        if last is None:
            self.first_sequence[input] = sequence
        elif sequence <= last:
            self.unknown_lost.add(input)
            return
        else:
            if sequence > last + 1:
                self.lost[input] += sequence - last - 1
                self.gap_wait_ms[input] = wait_ms
        self._sequence[input] = sequence

    def status(self) -> DiagnosticStatus:
        """Return the node's status now and start a new window."""
        counts = dict(self.counts())
        now = time.perf_counter()
        busy = self._window_s / max(now - self._window_start, 1e-9)
        received = sum(self.received.values())
        lag_s = math.nan
        if self.latest_stamp_ns is not None:
            lag_s = (self.node.get_clock().now().nanoseconds - self.latest_stamp_ns) / 1e9
        dropped = int(counts.get('dropped', 0))
        values = {f'received {name}': str(count) for name, count in self.received.items()}
        for name, count in self.lost.items():
            values[f'lost {name}'] = 'unknown' if name in self.unknown_lost else str(count)
        for name, sequence in self.first_sequence.items():
            values[f'first sequence {name}'] = str(sequence)
        lost = sum(self.lost.values())
        values.update({name: str(int(value)) for name, value in counts.items()})
        if self.values is not None:
            values.update(self.values())
        mean_ms = 1e3 * self.processing_s / received if received else 0.0  # per input
        values.update({
            'processing s': f'{self.processing_s:.3f}',
            'processing ms mean': f'{mean_ms:.2f}',
            'processing ms max': f'{1e3 * self._window_max_s:.2f}',
            'queue wait ms max': f'{self._window_wait_ms:.2f}',
            'busy %': f'{100.0 * busy:.1f}',
            'lag s': f'{lag_s:.3f}',
            'failed takes': str(self.failed_takes),
            IDLE_KEY: f'{time.monotonic() - self.last_input_s:.3f}',
        })  # fmt: skip
        problems: dict[str, str] = {}
        if dropped > self._last_dropped:
            problems['dropping'] = (
                f'dropping inputs ({dropped - self._last_dropped} since the last)'
            )
        if lost > self._last_lost:
            problems['lost'] = f'lost {lost - self._last_lost} {LOST_TEXT}'
        self._last_lost = lost
        if self.failed_takes > self._last_failed_takes:
            problems['failed takes'] = (
                f'rclpy failed to take {self.failed_takes - self._last_failed_takes} '
                'message(s), which are lost'
            )
        self._last_failed_takes = self.failed_takes
        if busy > BUSY_WARN and self.progress is None:  # paced: the player waits for it
            problems['busy'] = f'falling behind (busy {100.0 * busy:.0f} %)'
        self._log_change(problems, lost, dropped)
        self._last_dropped = dropped
        self._window_s = self._window_max_s = self._window_wait_ms = 0.0
        self._window_start = now
        status = DiagnosticStatus()
        status.name = self.node.get_fully_qualified_name()
        status.hardware_id = self.node.get_name()
        status.level = DiagnosticStatus.WARN if problems else DiagnosticStatus.OK
        summary = f'{received} received, {lost} lost, {dropped} dropped'
        if not self.received:  # no inputs (a bag player): its counts
            summary = ', '.join(f'{name} {value}' for name, value in counts.items()) or 'OK'
        status.message = '; '.join(problems.values()) or summary
        status.values = [KeyValue(key=key, value=value) for key, value in values.items()]
        return status

    def _node_log(self, level: str, text: str) -> None:
        # one call site per severity: an rclpy logger call site keeps its first severity
        if level == 'warning':
            self.node.get_logger().warning(text)
        else:
            self.node.get_logger().info(text)

    def _log_change(self, problems: Mapping[str, str], lost: int, dropped: int) -> None:
        """Log the kinds of problem that start, and the return to OK."""
        new = [kind for kind in problems if kind not in self._warned]
        if new:
            text = '; '.join(problems[kind] for kind in new)
            if 'lost' in new:
                text += (
                    f' ({lost} so far, by input: '
                    + ', '.join(
                        f'{name} {count}, the message after the last gap waited '
                        f'{self.gap_wait_ms.get(name, math.nan):.0f} ms'
                        for name, count in self.lost.items()
                        if count
                    )
                    + '; a queue that overflowed waited about its depth times the period, '
                    'one that DDS never delivered to about 0 ms)'
                )
            self._log('warning', f'WARN on /diagnostics: {text}')
            self._warned.update(new)
        self._ok_reports = 0 if problems else self._ok_reports + 1
        if self._warned and self._ok_reports >= OK_AGAIN_REPORTS:
            self._log(
                'info',
                f'OK again on /diagnostics (was: {", ".join(sorted(self._warned))}); '
                f'{lost} lost and {dropped} dropped so far',
            )
            self._warned.clear()

    def publish(self) -> None:
        """Publish the status (the timer's callback)."""
        array = DiagnosticArray()
        array.header.stamp = self.node.get_clock().now().to_msg()
        array.status = [self.status()]
        self.publisher.publish(array)
        if self.progress is not None:
            self.progress.report()
