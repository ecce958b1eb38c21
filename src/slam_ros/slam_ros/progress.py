"""Progress reports for paced replay: what a node has taken and published, per topic.

In paced replay (``bag_player`` with ``paced``, ``slam_run`` sets PACED_ENV for every node of
the graph) the player publishes the next message only once every node has finished with
what came before. For that, each node with ``slam_ros.diagnostics.Diagnostics`` publishes a
DiagnosticStatus on PROGRESS_TOPIC after every input or timer callback has returned (and
with every /diagnostics report): its fully qualified name, then ``taken <topic>`` (messages
taken from each subscribed topic, by the resolved topic name) and ``published <topic>``
(messages published on each topic) and ``subscribers <topic>`` (the subscriptions DDS has
matched to the node's publisher: a message published before a subscriber is matched never
reaches it, so the player starts only once the graph's own topics are all connected). The
player's rule (``slam_bringup.pacing``): the graph
is done with everything when every node has taken as many messages of each topic as the
player and the nodes have published on it.

A node that holds work back until its inputs stop (odometry_ingest's last keyframes) does
not decide that on the wall clock while a player runs (paced, the player pauses for as long
as the slowest node needs, seconds during a solve; timed, a busy machine can pause it): it
waits for END_TOPIC (std_msgs/Empty, END_QOS), which the player publishes once it has played
the bag (paced: once the graph is done with the whole bag).

Publishes are counted by wrapping the ``publish`` of each of the node's publishers, those
made before and after (``create_publisher`` is wrapped on the node). The reports, the
/diagnostics, /rosout, /parameter_events and /clock publishers are not counted.
"""

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
"""Set to 1 in a node's environment: the node reports its progress (module docstring)."""
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
