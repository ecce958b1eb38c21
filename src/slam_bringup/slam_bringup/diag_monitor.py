"""slam_diag: a live table of /diagnostics in the terminal, like rqt_robot_monitor.

Example: slam_diag --once -v --filter em_sam (listen --wait s, print once with every value).
Exit status with --once: 0 all OK, 1 a WARN, 3 an ERROR or STALE, 4 no diagnostics at all."""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from typing import Any

from slam_core.cli import PlainDescriptionHelpFormatter, console_main, positive_float

LEVELS = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}
SEVERITY = {'ERROR': 3, 'STALE': 2, 'WARN': 1, 'OK': 0}
COLORS = {'WARN': '\033[33m', 'ERROR': '\033[31m', 'STALE': '\033[31m'}
RESET = '\033[0m'
CLEAR = '\033[H\033[2J'
EXIT_BAD = 3
EXIT_NOTHING = 4


@dataclass
class Status:
    """The latest report of one status name."""

    name: str
    level: int
    message: str
    hardware_id: str
    values: list[tuple[str, str]] = field(default_factory=list)
    received_s: float = 0.0


class DiagnosticsTable:
    """The latest status per name, from DiagnosticArray messages."""

    def __init__(self, stale_s: float, name_filter: str = '') -> None:
        self.stale_s = stale_s
        self.name_filter = name_filter
        self.statuses: dict[str, Status] = {}
        self.arrays = 0

    def __call__(self, array: Any, now_s: float | None = None) -> None:
        now = time.monotonic() if now_s is None else now_s
        self.arrays += 1
        for status in array.status:
            if self.name_filter and self.name_filter not in status.name:
                continue
            level = status.level
            level = int.from_bytes(level, 'little') if isinstance(level, bytes) else int(level)
            self.statuses[status.name] = Status(
                status.name,
                level,
                status.message,
                status.hardware_id,
                [(kv.key, kv.value) for kv in status.values],
                now,
            )

    def level_of(self, status: Status, now_s: float) -> str:
        """The status's level name, STALE when its last update is older than stale_s."""
        if now_s - status.received_s > self.stale_s:
            return 'STALE'
        return LEVELS.get(status.level, f'LEVEL {status.level}')

    def worst(self, now_s: float) -> str | None:
        """The worst level of all statuses, or None when there is none."""
        levels = [self.level_of(s, now_s) for s in self.statuses.values()]
        return max(levels, key=lambda lv: SEVERITY.get(lv, 3)) if levels else None

    def render(self, now_s: float, *, verbose: bool = False, color: bool = False) -> str:
        """The table, worst first, then by name."""
        rows = sorted(
            ((self.level_of(s, now_s), s) for s in self.statuses.values()),
            key=lambda row: (-SEVERITY.get(row[0], 3), row[1].name),
        )
        if not rows:
            return f'no diagnostics yet ({self.arrays} messages on /diagnostics)'
        width = max(len(status.name) for _, status in rows)
        lines = [f'{"LEVEL":<6} {"NAME":<{width}}  {"AGE":>6}  MESSAGE']
        counts = dict.fromkeys(SEVERITY, 0)
        for level, status in rows:
            counts[level] = counts.get(level, 0) + 1
            age = f'{now_s - status.received_s:5.1f}s'
            text = f'{level:<6} {status.name:<{width}}  {age:>6}  {status.message}'
            if color and level in COLORS:
                text = f'{COLORS[level]}{text}{RESET}'
            lines.append(text)
            if verbose:
                lines.extend(f'{"":<6}   {key}: {value}' for key, value in status.values)
        summary = ', '.join(f'{n} {lv}' for lv, n in counts.items() if n)
        lines.append(f'{len(rows)} statuses: {summary}')
        return '\n'.join(lines)


def exit_code(worst: str | None) -> int:
    """--once's exit status for the worst level."""
    if worst is None:
        return EXIT_NOTHING
    return {'OK': 0, 'WARN': 1}.get(worst, EXIT_BAD)


def build_parser() -> argparse.ArgumentParser:
    """The command line of slam_diag."""
    parser = argparse.ArgumentParser(
        prog='slam_diag', description=__doc__, formatter_class=PlainDescriptionHelpFormatter
    )
    add = parser.add_argument
    add('--once', action='store_true', help='print the table once after --wait s, then exit')
    add(
        '--wait',
        type=positive_float,
        default=3.0,
        metavar='S',
        help='seconds to listen with --once',
    )
    add('--period', type=positive_float, default=1.0, metavar='S', help='seconds between redraws')
    add(
        '--stale',
        type=positive_float,
        default=5.0,
        metavar='S',
        help='a status older than S is STALE',
    )
    add('--filter', default='', metavar='TEXT', help='only statuses whose name contains TEXT')
    add('-v', '--verbose', action='store_true', help='print every key and value')
    add('--topic', default='/diagnostics', help='diagnostics topic (default /diagnostics)')
    add('--no-color', action='store_true', help='no colors, even in a terminal')
    return parser


@console_main('slam_diag')
def main(argv: list[str] | None = None) -> int:
    """Show the diagnostics table until Ctrl-C (or once)."""
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    from diagnostic_msgs.msg import DiagnosticArray

    from slam_bringup.graph_lookup import RosSession
    from slam_ros.qos import output_qos

    table = DiagnosticsTable(args.stale, args.filter)
    tty = sys.stdout.isatty()
    color = tty and not args.no_color
    with RosSession('slam_diag') as ros:
        ros.node.create_subscription(DiagnosticArray, args.topic, table, output_qos(depth=100))
        started = time.monotonic()
        next_draw = started + (args.wait if args.once else args.period)
        while ros.spin_once(0.05):
            now = time.monotonic()
            if now < next_draw:
                continue
            if args.once:
                break
            text = table.render(now, verbose=args.verbose, color=color)
            sys.stdout.write((CLEAR if tty else '') + text + ('\n' if tty else '\n\n'))
            sys.stdout.flush()
            next_draw = now + args.period
    now = time.monotonic()
    if args.once:
        print(table.render(now, verbose=args.verbose, color=color))  # noqa: T201
    print(f'slam_diag: {table.arrays} diagnostics messages received', file=sys.stderr)  # noqa: T201
    return exit_code(table.worst(now)) if args.once else 0


if __name__ == '__main__':
    sys.exit(main())
