"""The TF tree on /tf and /tf_static: parents, conflicts, chains (docs/design/ros_and_core.md)."""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from typing import Any

from slam_core.stamps import stamp_to_ns


@dataclass
class TfEdge:
    """One frame's link to its parent: static, or its sorted /tf stamps (int ns)."""

    parent: str
    static: bool
    stamps: list[int] = field(default_factory=list)


class TfTree:
    """Frames and their parents, as received; second parents go to ``conflicts``."""

    def __init__(self) -> None:
        self.edges: dict[str, TfEdge] = {}
        self.conflicts: list[str] = []
        self.transforms = 0

    def add(self, message: Any, *, static: bool) -> None:
        """Record a TFMessage from /tf_static (``static``) or /tf."""
        for transform in message.transforms:
            self.transforms += 1
            child = str(transform.child_frame_id).lstrip('/')
            parent = str(transform.header.frame_id).lstrip('/')
            stamp_ns = stamp_to_ns(transform.header.stamp)
            edge = self.edges.get(child)
            if edge is None:
                self.edges[child] = edge = TfEdge(parent, static)
            elif edge.parent != parent or edge.static != static:
                topic = '/tf_static' if static else '/tf'
                self.conflicts.append(
                    f'{child!r} has parent {edge.parent!r} '
                    f'({"/tf_static" if edge.static else "/tf"}) and {parent!r} ({topic})'
                )
                continue
            if not static:
                bisect.insort(edge.stamps, stamp_ns)

    def ancestors(self, frame: str) -> list[str]:
        """Return ``frame`` and its parents up to the root of its tree."""
        chain = [frame]
        while chain[-1] in self.edges and len(chain) <= len(self.edges):
            chain.append(self.edges[chain[-1]].parent)
        return chain

    def lookup_chain(self, target: str, source: str) -> list[str] | None:
        """Frames from ``source`` up to the common ancestor and down to ``target``, or None."""
        up = self.ancestors(source)
        down = self.ancestors(target)
        common = next((frame for frame in up if frame in down), None)
        if common is None:
            return None
        return up[: up.index(common) + 1] + down[: down.index(common)][::-1]

    def resolves(self, target: str, source: str, stamp_ns: int) -> bool:
        """Whether tf2 could look up ``source`` in ``target`` at ``stamp_ns``."""
        chain = self.lookup_chain(target, source)
        if chain is None:
            return False
        for frame in chain:
            edge = self.edges.get(frame)
            if edge is None or edge.static or edge.parent not in chain:
                continue
            index = bisect.bisect_left(edge.stamps, stamp_ns)
            exact = index < len(edge.stamps) and edge.stamps[index] == stamp_ns
            if not exact and (index == 0 or index == len(edge.stamps)):
                return False
        return True
