"""When a graph's nodes have worked off their inputs, by /diagnostics (docs/design/bringup.md)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.node import Node

from slam_ros.diagnostics import IDLE_KEY
from slam_ros.qos import output_qos

REPORT_GAP_S = 1.5  # reports of a node taking no long callback: its period (1 s) and jitter
SILENT_S = 3.0  # the longest to wait for the first report of a node: two periods and jitter


@dataclass(frozen=True)
class Report:
    """One status of a node: the idle seconds it reported and when it arrived (monotonic)."""

    idle_s: float
    received_s: float


class DrainWatch:
    """Follows the reports of the nodes ``names`` (fully qualified) and tells which are busy."""

    def __init__(
        self,
        names: Iterable[str],
        quiet_s: float,
        max_gap_s: float = REPORT_GAP_S,
        silent_s: float = SILENT_S,
    ) -> None:
        if not max_gap_s < quiet_s:
            raise ValueError(f'max_gap_s {max_gap_s} must be < quiet_s {quiet_s}')
        self.names = frozenset(names)
        self.quiet_s, self.max_gap_s, self.silent_s = quiet_s, max_gap_s, silent_s
        self._reports: dict[str, tuple[Report | None, Report]] = {}
        self._lock = threading.Lock()

    def add(self, array: DiagnosticArray, now_s: float | None = None) -> None:
        """Take the statuses of one /diagnostics message received at ``now_s``."""
        now_s = time.monotonic() if now_s is None else now_s
        for status in array.status:
            if status.name not in self.names:
                continue
            idle = next((v.value for v in status.values if v.key == IDLE_KEY), None)
            try:
                idle_s = float(idle) if idle is not None else math.nan
            except ValueError:
                idle_s = math.nan
            if math.isnan(idle_s):
                continue  # not a slam_ros.diagnostics report
            with self._lock:
                previous = self._reports.get(status.name)
                self._reports[status.name] = (
                    previous[1] if previous else None,
                    Report(idle_s, now_s),
                )

    def forget(self, name: str) -> None:
        """Stop following a node (its process has exited)."""
        with self._lock:
            self._reports.pop(name, None)
            self.names -= {name}

    def silent(self) -> list[str]:
        """Return the nodes that have not reported, sorted."""
        with self._lock:
            return sorted(self.names - set(self._reports))

    def quiet(self, name: str, now_s: float) -> bool:
        """Whether node ``name`` is quiet at ``now_s`` (the rule: docs/design/bringup.md)."""
        with self._lock:
            previous, last = self._reports[name]
        return (
            previous is not None
            and previous.idle_s >= self.quiet_s
            and last.idle_s >= self.quiet_s
            and last.received_s - previous.received_s <= self.max_gap_s
            and now_s - last.received_s <= self.max_gap_s
        )

    def busy(self, since_s: float, now_s: float | None = None) -> list[str]:
        """The nodes not quiet at ``now_s`` (silent ones until ``since_s + silent_s``), sorted."""
        now_s = time.monotonic() if now_s is None else now_s
        with self._lock:
            names = sorted(self._reports)
        busy = [name for name in names if not self.quiet(name, now_s)]
        if now_s - since_s < self.silent_s:
            busy = sorted(busy + self.silent())
        return busy


def listen(context: Context, watch: DrainWatch, *also: Callable[[DiagnosticArray], None]) -> Node:
    """A node (``slam_run``) feeding each /diagnostics message to ``watch`` and to ``also``."""
    node = Node(
        'slam_run',
        context=context,
        use_global_arguments=False,
        start_parameter_services=False,
    )

    def take(array: DiagnosticArray) -> None:
        watch.add(array)
        for consumer in also:
            consumer(array)

    node.create_subscription(DiagnosticArray, '/diagnostics', take, output_qos(depth=100))
    return node
