"""Paced replay, the player's side: is the graph done with everything published so far?"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from slam_ros.progress import PUBLISHED, SUBSCRIBERS, TAKEN


@dataclass(frozen=True)
class Shortfall:
    """A node short of the messages published on a topic (or a publisher short of matches)."""

    node: str
    topic: str
    taken: int
    published: int
    verb: str = 'took'

    def __str__(self) -> str:
        return f'{self.node} {self.verb} {self.taken} of {self.published} on {self.topic}'


class PacedGate:
    """The latest progress report of each node (the rule: docs/design/bringup.md)."""

    def __init__(self, expected: Iterable[str] = ()) -> None:
        self.expected = tuple(expected)
        self._taken: dict[str, dict[str, int]] = {}
        self._published: dict[str, dict[str, int]] = {}
        self._subscribers: dict[str, dict[str, int]] = {}

    def update(self, node: str, values: Iterable[tuple[str, str]]) -> None:
        """Take a node's report, (key, value) pairs; keys other than the counts are ignored."""
        taken: dict[str, int] = {}
        published: dict[str, int] = {}
        subscribers: dict[str, int] = {}
        for key, value in values:
            try:
                count = int(value)
            except ValueError:
                continue
            if key.startswith(TAKEN):
                taken[key[len(TAKEN) :]] = count
            elif key.startswith(PUBLISHED):
                published[key[len(PUBLISHED) :]] = count
            elif key.startswith(SUBSCRIBERS):
                subscribers[key[len(SUBSCRIBERS) :]] = count
        self._subscribers[node] = subscribers
        self._taken[node], self._published[node] = taken, published  # each swapped whole

    def missing(self) -> list[str]:
        """The expected nodes that have not reported yet."""
        return [node for node in self.expected if node not in self._taken]

    def unmatched(self, player_subscribers: Mapping[str, int]) -> list[Shortfall]:
        """Publishers (player's, nodes') not yet matched with every node that takes their topic."""
        takers: dict[str, int] = {}
        for counts in list(self._taken.values()):
            for topic in counts:
                takers[topic] = takers.get(topic, 0) + 1
        publishers = [('the player', dict(player_subscribers))]
        publishers += list(self._subscribers.items())
        short = []
        for node, counts in publishers:
            for topic, matched in counts.items():
                if matched < takers.get(topic, 0):
                    short.append(Shortfall(node, topic, matched, takers[topic], 'is matched with'))
        return short

    def shortfalls(self, player_published: Mapping[str, int]) -> list[Shortfall]:
        """What keeps the graph from being done with all published so far (empty: done)."""
        published = dict(player_published)
        for counts in list(self._published.values()):
            for topic, count in counts.items():
                published[topic] = published.get(topic, 0) + count
        short = []
        for node, counts in list(self._taken.items()):
            for topic, taken in counts.items():
                if topic in published and taken < published[topic]:
                    short.append(Shortfall(node, topic, taken, published[topic]))
        return short
