"""Respawn of GRAPH nodes (slam_run --processes), and ``failing_node`` (docs/design/bringup.md)."""

from __future__ import annotations

import dataclasses
import subprocess
import time
import traceback
from collections.abc import Callable, MutableSequence, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from rclpy.node import Node

from slam_bringup.graph_nodes import NodeDescription

MAX_DELAY_S = 30.0
RESET_AFTER_S = 60.0


class Supervised(Protocol):
    """What the runner keeps of a node's process (runner.Child)."""

    description: NodeDescription
    process: subprocess.Popen[bytes]


def respawn_delay_s(first_s: float, attempt: int) -> float:
    """The back-off before restart ``attempt`` (1, 2, ...): doubled each time, capped."""
    return min(first_s * 2.0 ** (attempt - 1), max(MAX_DELAY_S, first_s))


def restart_description(description: NodeDescription) -> NodeDescription:
    """The description a restart runs: the entry's respawn_parameters after its own."""
    if not description.respawn_parameters:
        return description
    return dataclasses.replace(
        description, parameters=(*description.parameters, description.respawn_parameters)
    )


def warn_if_respawn_ignored(
    descriptions: Sequence[NodeDescription], say: Callable[[str], None]
) -> None:
    """One process cannot restart one node: say which entries' respawn is ignored."""
    keys = [d.key for d in descriptions if d.respawn]
    if keys:
        say(
            f'warning: respawn is ignored in one process ({", ".join(keys)}): a node '
            'cannot be restarted alone; run with --processes'
        )


@dataclass
class Respawner:
    """Restarts the children whose description asks for it, with a back-off, through ``start``."""

    start: Callable[[NodeDescription], Supervised]
    say: Callable[[str], None]
    attempts: dict[str, int] = field(default_factory=dict)
    started_at: dict[str, float] = field(default_factory=dict)
    due: dict[str, tuple[float, int]] = field(default_factory=dict)  # name -> (time, index)
    first: dict[str, NodeDescription] = field(default_factory=dict)  # as the GRAPH gave it

    @property
    def waiting(self) -> bool:
        """True while a restart is due."""
        return bool(self.due)

    def exited(self, children: Sequence[Supervised], index: int, code: int) -> bool:
        """Schedule a restart of ``children[index]`` if it asks for one; return whether."""
        description = children[index].description
        if not description.respawn or code == 0:
            return False
        name = description.fully_qualified_name
        self.first.setdefault(name, description)
        now = time.monotonic()
        if now - self.started_at.get(name, now) >= RESET_AFTER_S:
            self.attempts[name] = 0
        attempt = self.attempts.get(name, 0) + 1
        self.attempts[name] = attempt
        delay = respawn_delay_s(description.respawn_delay_s, attempt)
        self.say(
            f'{description.name} exited with code {code}; respawning in {delay:g} s '
            f'(attempt {attempt})'
        )
        self.due[name] = (now + delay, index)
        return True

    def poll(self, children: MutableSequence[Supervised]) -> None:
        """Start the restarts that are due, each in its dead child's place."""
        now = time.monotonic()
        for name, (when, index) in list(self.due.items()):
            if when <= now:
                del self.due[name]
                children[index] = self.start(restart_description(self.first[name]))
                self.started_at[name] = time.monotonic()


def failing_node(
    error: BaseException, nodes: Sequence[tuple[NodeDescription, Node]]
) -> str | None:
    """The name of the node whose method raised ``error`` (innermost on its traceback), or None."""
    found = None
    for frame, _ in traceback.walk_tb(error.__traceback__):
        owner = frame.f_locals.get('self')
        for description, node in nodes:
            if owner is node:
                found = description.fully_qualified_name
    return found
