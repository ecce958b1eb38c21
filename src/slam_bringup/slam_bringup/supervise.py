"""Respawn of GRAPH nodes that set ``respawn: true`` (``slam_run --processes``), and naming
the node whose callback raised in one process (``failing_node``).

When such a node's process dies (any exit code but 0, which only a requested stop gives),
the runner starts it again after a back-off: ``respawn_delay_s`` (default 1 s) for the
first restart, doubled for each further one up to MAX_DELAY_S; a process that ran for
RESET_AFTER_S or longer before it died starts the count again. The restart gets the entry's
``respawn_parameters`` after its other parameters: ``{resume_from: auto}`` makes a node
with checkpoints (em_sam_mapper, monoslam) load its checkpoint (``checkpoint_file``) when
there is one, so the restarted node continues where its last checkpoint left off. Each
restart is logged as ``slam_run: NODE exited with code X; respawning in Y s (attempt N)``.

In one process a single node cannot be restarted (a crash takes the whole process):
``respawn`` is ignored there, with a warning naming the entries.
"""

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
    """Restarts the children whose description asks for it, with a back-off.

    ``start`` starts a description's process and returns the new child.
    """

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
    """The graph's name of the node whose method raised ``error`` (the innermost on its
    traceback), or None when no node's code is on it."""
    found = None
    for frame, _ in traceback.walk_tb(error.__traceback__):
        owner = frame.f_locals.get('self')
        for description, node in nodes:
            if owner is node:
                found = description.fully_qualified_name
    return found
