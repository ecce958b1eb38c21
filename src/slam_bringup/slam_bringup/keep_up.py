"""Whether a graph keeps up with its input, said once per node (docs/design/bringup.md)."""

from __future__ import annotations

from collections.abc import Callable, Iterable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

from slam_bringup.graph_types import PlayerSpec

LOSS_WORDS = ('lost', 'dropping inputs')


def remedies(*, has_player: bool, paced: bool, processes: bool) -> list[str]:
    """The slam_run options that would keep every message, for this run."""
    if paced:  # the player waits for the nodes: nothing to lose, nothing to suggest
        return []
    options = []
    if has_player:
        options.append('--paced (the player waits for the nodes: every message, on any machine)')
    if not processes:
        options.append('--processes (one process per node: each node gets a core)')
    if has_player:
        options.append('a lower --rate')
    return options


def keep_up_options(player: PlayerSpec | None, *, processes: bool) -> list[str]:
    """``remedies`` for a graph with ``player`` (None: live) run with or without --processes."""
    return remedies(
        has_player=player is not None, paced=bool(player and player.paced), processes=processes
    )


def start_note(options: list[str]) -> str | None:
    """What slam_run says at start of a free-running run, or None."""
    if not options:
        return None
    return (
        'free-running: a node that cannot keep up loses messages (counted on /diagnostics, '
        'slam_diag shows them); to keep every one use ' + ', or '.join(options)
    )


class KeepUpHint:
    """Says once per node of ``names`` when it first reports a loss."""

    def __init__(
        self, names: Iterable[str], options: list[str], say: Callable[[str], None]
    ) -> None:
        self.names = frozenset(names)
        self.options = options
        self.say = say
        self.told: set[str] = set()

    def add(self, array: DiagnosticArray) -> None:
        """Take one /diagnostics message."""
        if not self.options:
            return
        for status in array.status:
            if (
                status.name in self.names
                and status.name not in self.told
                and status.level == DiagnosticStatus.WARN
                and any(word in status.message for word in LOSS_WORDS)
            ):
                self.told.add(status.name)
                self.say(
                    f'{status.name} cannot keep up ({status.message}); '
                    'to keep every message use ' + ', or '.join(self.options)
                )
