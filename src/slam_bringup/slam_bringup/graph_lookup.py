"""Find a topic or service on the live ROS graph by its name or a unique tail of it."""

from __future__ import annotations

import difflib
import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING

from slam_core.errors import SlamError

if TYPE_CHECKING:
    from rclpy.node import Node

POLL_S = 0.05


class DiscoveryError(SlamError):
    """A topic or service was not found on the ROS graph in time."""


@dataclass(frozen=True)
class Found:
    """A resolved graph name and its interface type (``pkg/msg/Name`` or ``pkg/srv/Name``)."""

    name: str
    type_name: str


def match_name(wanted: str, available: Sequence[str]) -> str | None:
    """The one name in ``available`` that ``wanted`` denotes (exact or unique tail), or None."""
    absolute = '/' + wanted.lstrip('/')
    if absolute in available:
        return absolute
    tail = '/' + wanted.strip('/')
    ends = [name for name in available if name.endswith(tail)]
    return ends[0] if len(ends) == 1 else None


def not_found_message(kind: str, wanted: str, available: Sequence[str], waited_s: float) -> str:
    """The error text for ``wanted`` not found among ``available`` after ``waited_s``."""
    tail = '/' + wanted.strip('/')
    ambiguous = [name for name in available if name.endswith(tail)]
    if len(ambiguous) > 1:
        return (
            f'{kind} {wanted!r} is ambiguous: {", ".join(sorted(ambiguous))}; give the full name'
        )
    close = difflib.get_close_matches('/' + wanted.lstrip('/'), list(available), n=3, cutoff=0.5)
    hint = f'; did you mean {" or ".join(repr(c) for c in close)}?' if close else ''
    listing = ', '.join(sorted(available)) if available else 'none'
    return (
        f'no {kind} {wanted!r} on the ROS graph after {waited_s:.1f} s{hint} '
        f'({kind}s seen: {listing}). Is the graph running, in this ROS_DOMAIN_ID '
        'and DDS profile (scripts/env.sh)?'
    )


def wait_for(
    kind: str,
    wanted: str,
    list_entities: Callable[[], list[tuple[str, list[str]]]],
    timeout_s: float,
) -> Found:
    """Poll ``list_entities()`` until ``wanted`` resolves; DiscoveryError: not found, 2+ types."""
    started = time.monotonic()
    while True:
        entities = dict(list_entities())
        name = match_name(wanted, list(entities))
        if name is not None:
            types = entities[name]
            if len(types) != 1:
                raise DiscoveryError(
                    f'{kind} {name!r} is offered with several types ({", ".join(types)}); '
                    'give one with --type'
                )
            return Found(name, types[0])
        waited = time.monotonic() - started
        if waited >= timeout_s:
            raise DiscoveryError(not_found_message(kind, wanted, list(entities), waited))
        time.sleep(POLL_S)


def find_topic(node: Node, topic: str, timeout_s: float) -> Found:
    """Wait for a publisher of ``topic`` (see ``wait_for``)."""

    def publishers() -> list[tuple[str, list[str]]]:
        return [
            (name, types)
            for name, types in node.get_topic_names_and_types()
            if node.count_publishers(name) > 0
        ]

    return wait_for('topic', topic, publishers, timeout_s)


def find_service(node: Node, service: str, timeout_s: float) -> Found:
    """Wait for a server of ``service`` (see ``wait_for``)."""
    return wait_for('service', service, node.get_service_names_and_types, timeout_s)


class RosSession(AbstractContextManager['RosSession']):
    """rclpy initialized with one quiet node for a CLI; ``spin_once`` is False after Ctrl-C."""

    def __init__(self, prog: str) -> None:
        import os

        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self._rclpy = rclpy
        rclpy.init(args=[prog])
        self.node = Node(f'{prog}_{os.getpid()}', enable_rosout=False)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)

    def spin_once(self, timeout_s: float) -> bool:
        """Run what is ready, waiting at most ``timeout_s``; False once shut down."""
        from rclpy.executors import ExternalShutdownException

        if not self._rclpy.ok():
            return False
        try:
            self.executor.spin_once(timeout_sec=timeout_s)
        except (KeyboardInterrupt, ExternalShutdownException):
            return False
        return self._rclpy.ok()

    def __exit__(self, *exc: object) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown()
