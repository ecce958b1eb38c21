"""A validated GRAPH file's types (``graph`` reads and checks the file into them)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slam_core.errors import GraphError

ParameterSource = Path | dict[str, Any]
Remapping = tuple[str, str]


@dataclass(frozen=True)
class NodeSpec:
    """One entry of ``graph.nodes``; ``key`` is its path in the file (``graph.nodes[2]``)."""

    key: str
    name: str
    package: str
    executable: str
    plugin: str | None
    namespace: str
    parameters: tuple[ParameterSource, ...]
    remappings: tuple[Remapping, ...]
    respawn: bool = False
    respawn_delay_s: float = 1.0
    respawn_parameters: dict[str, Any] | None = None


@dataclass(frozen=True)
class PlayerSpec:
    """``graph.player``: bag_player parameters; None leaves the node's default."""

    bag: Path | None = None
    rate: float | None = None
    start_offset_s: float | None = None
    topics: tuple[str, ...] = ()
    remap: tuple[Remapping, ...] = ()
    replayable_topics: tuple[str, ...] = ()
    loop: bool | None = None
    clock_hz: float | None = None
    wait_for_subscribers_s: float | None = None
    progress_period_s: float | None = None
    paced: bool | None = None
    paced_nodes: tuple[str, ...] = ()  # slam_run sets the graph's nodes when paced
    paced_timeout_s: float | None = None


@dataclass(frozen=True)
class RecorderSpec:
    """``graph.recorder``: bag_recorder parameters; None leaves the node's default."""

    output: Path | None = None
    topics: tuple[str, ...] = ()
    exclude: tuple[str, ...] | None = None
    discovery_period_s: float | None = None
    queue_depth: int | None = None
    flush_period_s: float | None = None


@dataclass(frozen=True)
class Graph:
    """A validated GRAPH file."""

    path: Path
    description: str
    nodes: tuple[NodeSpec, ...]
    player: PlayerSpec | None
    recorder: RecorderSpec | None
    use_sim_time: bool | None
    exit_when_player_done: bool

    def error(self, key: str, message: str) -> GraphError:
        """Return a GraphError ``graph '<file>': <key>: <message>``."""
        return graph_error(self.path, key, message)


def graph_error(path: Path, key: str, message: str) -> GraphError:
    """Return a GraphError ``graph '<file>': <key>: <message>``."""
    return GraphError(f'graph {str(path)!r}: {key}: {message}')
