"""A node's progress reports for paced replay, per topic (docs/design/ros_and_core.md)."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

PROGRESS_TOPIC = '/slam/progress'
PACED_ENV = 'SLAM_PACED'
"""Set to 1 in a node's environment: the node reports its progress."""
PROGRESS_QOS = QoSProfile(
    depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE
)
END_TOPIC = '/slam/end_of_input'
END_QOS = QoSProfile(
    depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)
NOT_COUNTED = ('/diagnostics', PROGRESS_TOPIC, '/rosout', '/parameter_events', '/clock')
TAKEN, PUBLISHED, SUBSCRIBERS = 'taken ', 'published ', 'subscribers '


def paced() -> bool:
    """True when this process runs nodes of a paced replay (PACED_ENV is 1)."""
    return os.environ.get(PACED_ENV, '') == '1'


class Progress:
    """Counts a node's publishes per topic and publishes its progress reports."""

    def __init__(self, node: Node, taken: Callable[[], Mapping[str, int]]) -> None:
        self.node, self.taken = node, taken
        self.published: dict[str, int] = {}
        self._publishers: dict[str, Publisher] = {}
        create = node.create_publisher
        self.publisher = create(DiagnosticStatus, PROGRESS_TOPIC, PROGRESS_QOS)
        for publisher in list(node.publishers):
            self._count(publisher)

        def create_counted(*args: Any, **kwargs: Any) -> Publisher:
            publisher = create(*args, **kwargs)
            self._count(publisher)
            return publisher

        node.create_publisher = create_counted  # type: ignore[method-assign]

    def _count(self, publisher: Publisher) -> None:
        topic = publisher.topic_name
        if topic in NOT_COUNTED or topic in self.published:
            return
        self.published[topic] = 0
        self._publishers[topic] = publisher
        publish = publisher.publish

        def counted(message: Any) -> None:
            publish(message)
            self.published[topic] += 1

        publisher.publish = counted  # type: ignore[method-assign,assignment]

    def report(self) -> None:
        """Publish what the node has taken and published so far."""
        status = DiagnosticStatus()
        status.name = self.node.get_fully_qualified_name()
        values = [KeyValue(key=TAKEN + t, value=str(n)) for t, n in self.taken().items()]
        values += [KeyValue(key=PUBLISHED + t, value=str(n)) for t, n in self.published.items()]
        values += [
            KeyValue(key=SUBSCRIBERS + t, value=str(p.get_subscription_count()))
            for t, p in self._publishers.items()
        ]
        status.values = values
        self.publisher.publish(status)
