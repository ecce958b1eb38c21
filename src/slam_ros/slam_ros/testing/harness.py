"""Nodes, probes and waits with deadlines over real DDS (docs/design/ros_and_core.md)."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

DEFAULT_TIMEOUT_S = 20.0
POLL_S = 0.01


def reliable_qos(depth: int = 1000, *, latched: bool = False) -> QoSProfile:
    """Reliable keep-last QoS for probes (deep enough to miss nothing in a test)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


_STOPPED: list[str] = []
"""Why the latest harness's executor stopped (an exception escaped a node's callback), if it
did: nothing spins any more, so ``wait_until`` fails at once instead of at its deadline."""


def wait_until(
    predicate: Callable[[], bool], *, timeout_s: float = DEFAULT_TIMEOUT_S, what: str = 'condition'
) -> None:
    """Poll ``predicate`` until true (TimeoutError at the deadline, RuntimeError if stopped)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if _STOPPED:
            raise RuntimeError(f'waiting for {what}: {_STOPPED[-1]}')
        if time.monotonic() > deadline:
            raise TimeoutError(f'timed out after {timeout_s:.1f} s waiting for {what}')
        time.sleep(POLL_S)


@dataclass
class Collector:
    """Messages received on one topic, in arrival order, with monotonic receive times (ns)."""

    topic: str
    messages: list[Any] = field(default_factory=list)
    received_ns: list[int] = field(default_factory=list)
    _condition: threading.Condition = field(default_factory=threading.Condition)

    def __call__(self, message: Any) -> None:
        with self._condition:
            self.messages.append(message)
            self.received_ns.append(time.monotonic_ns())
            self._condition.notify_all()

    def __len__(self) -> int:
        with self._condition:
            return len(self.messages)

    def wait_for_count(self, count: int, *, timeout_s: float = DEFAULT_TIMEOUT_S) -> list[Any]:
        """Block until at least ``count`` messages arrived; return a snapshot of all."""
        deadline = time.monotonic() + timeout_s
        with self._condition:
            while len(self.messages) < count:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(
                        f'timed out after {timeout_s:.1f} s on {self.topic!r}: '
                        f'{len(self.messages)} of {count} messages'
                    )
                self._condition.wait(remaining)
            return list(self.messages)

    def wait_for(
        self, predicate: Callable[[Any], bool], *, timeout_s: float = DEFAULT_TIMEOUT_S
    ) -> Any:
        """Block until a message satisfying ``predicate`` arrives; return it."""
        deadline = time.monotonic() + timeout_s
        seen = 0
        with self._condition:
            while True:
                for message in self.messages[seen:]:
                    if predicate(message):
                        return message
                seen = len(self.messages)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(
                        f'timed out after {timeout_s:.1f} s on {self.topic!r}: none of '
                        f'{seen} messages matched'
                    )
                self._condition.wait(remaining)


@dataclass
class NodeProcess:
    """A node started as a subprocess; its output goes to a log file."""

    name: str
    process: subprocess.Popen[bytes]
    log_path: Path

    def log(self) -> str:
        """Return everything the process printed so far."""
        return self.log_path.read_text(encoding='utf-8', errors='replace')

    def wait_for_line(self, timeout_s: float, *parts: str) -> str:
        """Wait up to ``timeout_s`` for a printed line holding all ``parts``; return it."""

        def line() -> str | None:
            return next((x for x in self.log().splitlines() if all(p in x for p in parts)), None)

        wait_until(
            lambda: line() is not None, timeout_s=timeout_s, what=f'a log line with {parts}'
        )
        return str(line())

    def stop(self, *, timeout_s: float = 10.0) -> int:
        """SIGINT, then SIGTERM, then SIGKILL; return the exit code."""
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if self.process.poll() is not None:
                break
            self.process.send_signal(sig)
            try:
                self.process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                continue
        return self.process.wait()


class RosHarness:
    """One test's ROS graph: in-process nodes, subprocess nodes, probes and publishers."""

    def __init__(self, log_dir: Path, *, name: str = 'test_harness') -> None:
        self.log_dir = log_dir
        self.node = Node(name)
        # Single-threaded on purpose: Jazzy's MultiThreadedExecutor busy-loops while
        # callbacks are queued (ros2/rclpy#1452) and starves other Python threads.
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._nodes: list[Node] = []
        self._processes: list[NodeProcess] = []
        self._thread = threading.Thread(target=self._spin, name='harness-executor', daemon=True)
        self._running = True
        _STOPPED.clear()
        self._thread.start()

    def _spin(self) -> None:
        try:
            while self._running and rclpy.ok():
                self.executor.spin_once(timeout_sec=0.05)
        except Exception as error:  # a node's callback raised: the graph stops here
            _STOPPED.append(
                f'the harness executor stopped: {type(error).__name__}: {error} '
                '(an exception escaped a node callback; its traceback follows the test)'
            )
            raise

    # -- nodes ----------------------------------------------------------------------------
    def add_node(self, node: Node) -> Node:
        """Spin an in-process node in the harness executor until the test ends."""
        self._nodes.append(node)
        self.executor.add_node(node)
        return node

    def remove_node(self, node: Node) -> None:
        """Stop spinning an in-process node and destroy it (a node that stops mid-test)."""
        self._nodes.remove(node)
        self.executor.remove_node(node)
        node.destroy_node()

    def start_process(
        self,
        name: str,
        command: Sequence[str],
        *,
        env: dict[str, str] | None = None,
        cwd: Path | None = None,
    ) -> NodeProcess:
        """Start ``command`` as a subprocess in this domain, in ``cwd`` (None: here)."""
        log_path = self.log_dir / f'{name}.log'
        log_file = log_path.open('wb')
        process = subprocess.Popen(
            list(command),
            stdout=log_file,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env={**os.environ, **(env or {})},
            cwd=cwd,
        )
        log_file.close()
        handle = NodeProcess(name, process, log_path)
        self._processes.append(handle)
        return handle

    # -- topics ---------------------------------------------------------------------------
    def collect(self, topic: str, msg_type: type, qos: QoSProfile | None = None) -> Collector:
        """Subscribe the probe node to ``topic``; return the collector of what arrives."""
        collector = Collector(topic)
        self.node.create_subscription(msg_type, topic, collector, qos or reliable_qos())
        return collector

    def publisher(self, topic: str, msg_type: type, qos: QoSProfile | None = None) -> Publisher:
        """Create a publisher on the probe node."""
        return self.node.create_publisher(msg_type, topic, qos or reliable_qos())

    def wait_for_subscribers(
        self, publisher: Publisher, count: int = 1, *, timeout_s: float = DEFAULT_TIMEOUT_S
    ) -> None:
        """Wait until ``publisher`` is matched with ``count`` subscriptions."""
        wait_until(
            lambda: publisher.get_subscription_count() >= count,
            timeout_s=timeout_s,
            what=f'{count} subscriber(s) on {publisher.topic_name!r}',
        )

    def wait_for_publishers(
        self, topic: str, count: int = 1, *, timeout_s: float = DEFAULT_TIMEOUT_S
    ) -> None:
        """Wait until ``count`` publishers on ``topic`` are discovered."""
        wait_until(
            lambda: self.node.count_publishers(topic) >= count,
            timeout_s=timeout_s,
            what=f'{count} publisher(s) on {topic!r}',
        )

    # -- teardown -------------------------------------------------------------------------
    def close(self) -> None:
        """Stop subprocesses, destroy in-process nodes, stop the executor."""
        for handle in self._processes:
            handle.stop()
        self._running = False
        self._thread.join(timeout=10.0)
        _STOPPED.clear()  # a later wait is not this graph's
        for node in [*self._nodes, self.node]:
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown(timeout_sec=5.0)
