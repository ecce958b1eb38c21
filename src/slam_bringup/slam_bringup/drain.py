"""When the nodes of a graph have worked off their inputs, from what they report on
/diagnostics (``slam_ros.diagnostics``): the rule slam_run follows, in one process and with
``--processes``, before it stops a graph whose player has finished.

Every processing node publishes its status once a second (``Diagnostics``, one timer in the
node's executor), with ``idle s``: the seconds since an input callback last ended. A node is
*quiet* when its last two reports both say it took no input for ``quiet_s`` and they came at
most ``max_gap_s`` apart, the last at most ``max_gap_s`` ago:

- a report is a timer callback of the node's executor, which takes a queued message right
  after it; a message queued at the first report therefore shows in the second (idle < gap),
  so two quiet reports mean its queues were empty;
- a gap longer than ``max_gap_s`` means a callback held the executor in between (a long
  solve), and messages may have queued meanwhile: wait for the next pair;
- ``quiet_s`` must cover the outputs a node makes from a timer once its inputs stop
  (odometry_ingest publishes its held-back keyframes after ``idle_flush_s``): the node that
  takes them is not quiet until it has had them for ``quiet_s``.

Only the graph's own nodes count (their fully qualified names), and only those that report
``idle s``: the player's and the recorder's reports are ignored (a recorder that records
/diagnostics takes an input every second, from the nodes' reports and its own), and so are
those of other graphs on the same DDS domain. A node of the graph that has not reported yet
is busy for ``silent_s`` from when the wait began (its first report comes a period after it
started, and a short bag can end before), then it is not waited for (a driver without
``slam_ros.diagnostics``).
"""

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
        """Whether node ``name`` has been quiet (module docstring) at ``now_s``."""
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
        """Return the nodes not quiet at ``now_s`` when the wait began at ``since_s``: those
        that reported and are not quiet, and until ``since_s + silent_s`` those that have not
        reported; sorted."""
        now_s = time.monotonic() if now_s is None else now_s
        with self._lock:
            names = sorted(self._reports)
        busy = [name for name in names if not self.quiet(name, now_s)]
        if now_s - since_s < self.silent_s:
            busy = sorted(busy + self.silent())
        return busy


def listen(context: Context, watch: DrainWatch, *also: Callable[[DiagnosticArray], None]) -> Node:
    """Return a node (``slam_run``) that feeds every /diagnostics message into ``watch`` (and
    into each of ``also``); spin it with the executor of ``context``."""
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
