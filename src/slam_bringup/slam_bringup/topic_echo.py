"""slam_echo: print a topic's messages as YAML, like `ros2 topic echo`, without a ROS install.

Example: slam_echo em_sam/path --rate 1 --field poses (YAML documents separated by '---')."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from slam_core.cli import PlainDescriptionHelpFormatter, console_main, positive_float
from slam_core.errors import SlamError

TRUNCATE = 128
EXIT_TIMEOUT = 1


def build_parser() -> argparse.ArgumentParser:
    """The command line of slam_echo."""
    parser = argparse.ArgumentParser(
        prog='slam_echo',
        description=__doc__,
        formatter_class=PlainDescriptionHelpFormatter,
    )
    add = parser.add_argument
    add('topic', help='topic name, e.g. /em_sam/moveable (a unique tail works)')
    add('--type', help='message type, e.g. nav_msgs/msg/Path (default: from the graph)')
    add('--once', action='store_true', help='print one message, then exit')
    add('--count', type=int, metavar='N', help='print N messages, then exit')
    add('--rate', type=positive_float, metavar='HZ', help='print at most HZ messages a second')
    add('--field', metavar='A.B', help='print only this field, e.g. header.stamp')
    add('--timeout', type=positive_float, metavar='S', help='exit 1 after S s without a message')
    add('--wait', type=positive_float, default=5.0, metavar='S', help='wait S s for a publisher')
    add('--full-length', action='store_true', help='print long arrays and strings whole')
    add('--no-arr', action='store_true', help='leave arrays out')
    add('--depth', type=int, default=10, metavar='N', help='subscription queue depth')
    return parser


def select_field(message: Any, path: str | None) -> Any:
    """The part of ``message`` at the dotted ``path``; SlamError when a segment is not there."""
    from slam_bringup.message_yaml import is_message

    if not path:
        return message
    for segment in path.split('.'):
        if is_message(message) and segment in message.get_fields_and_field_types():
            message = getattr(message, segment)
        elif not is_message(message) and segment.isdigit() and int(segment) < len(message):
            message = message[int(segment)]
        else:
            has = (
                ', '.join(message.get_fields_and_field_types())
                if is_message(message)
                else f'{len(message)} items'
            )
            raise SlamError(f'--field {path}: no {segment!r} here (it has: {has})')
    return message


class Echo:
    """The printing side: rate limit, count, summary."""

    def __init__(
        self,
        args: argparse.Namespace,
        out: Any = sys.stdout,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.args = args
        self.out = out
        self.clock = clock
        self.received = 0
        self.printed = 0
        self.skipped = 0
        self.first_s: float | None = None
        self.last_s: float | None = None
        self._last_printed_s = -float('inf')
        self.limit = 1 if args.once else args.count

    @property
    def done(self) -> bool:
        """Whether --once or --count is satisfied."""
        return self.limit is not None and self.printed >= self.limit

    def __call__(self, message: Any) -> None:
        from slam_bringup.message_yaml import message_to_data, to_yaml

        now = self.clock()
        self.received += 1
        self.first_s = now if self.first_s is None else self.first_s
        self.last_s = now
        if self.done or now - self._last_printed_s < 1.0 / (self.args.rate or float('inf')):
            self.skipped += 1
            return
        self._last_printed_s = now
        part = select_field(message, self.args.field)
        data = message_to_data(
            part, truncate=None if self.args.full_length else TRUNCATE, arrays=not self.args.no_arr
        )
        self.out.write(to_yaml(data) + '---\n')
        self.out.flush()
        self.printed += 1

    def summary(self, topic: str) -> str:
        """One line: received, printed, skipped, mean rate."""
        rate = ''
        if self.received > 1 and self.first_s is not None and self.last_s is not None:
            span = self.last_s - self.first_s
            rate = f', {(self.received - 1) / span:.2f} Hz' if span > 0 else ''
        return (
            f'slam_echo: {topic}: {self.received} received, {self.printed} printed, '
            f'{self.skipped} skipped{rate}'
        )


def subscription_qos(offered: Sequence[Any], depth: int) -> Any:
    """The publishers' QoS (see slam_ros.qos.matching_qos)."""
    from slam_ros.qos import matching_qos

    return matching_qos([info.qos_profile for info in offered], depth)


@console_main('slam_echo')
def main(argv: list[str] | None = None) -> int:
    """Echo one topic until Ctrl-C, --once, --count or --timeout."""
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    for name in ('count', 'depth'):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise SlamError(f'--{name} must be at least 1, got {getattr(args, name)}')
    from slam_bringup.graph_lookup import Found, RosSession, find_topic
    from slam_ros.typesys import message_class

    echo = Echo(args)
    with RosSession('slam_echo') as ros:
        if args.type:
            found = Found('/' + args.topic.lstrip('/'), args.type)
        else:
            found = find_topic(ros.node, args.topic, args.wait)
        cls = message_class(found.type_name, topic=found.name)
        qos = subscription_qos(ros.node.get_publishers_info_by_topic(found.name), args.depth)
        ros.node.create_subscription(cls, found.name, echo, qos)
        started = time.monotonic()
        timed_out = ''
        while not echo.done and ros.spin_once(0.1):
            if args.timeout and echo.received == 0 and time.monotonic() - started > args.timeout:
                publishers = ros.node.count_publishers(found.name)
                timed_out = (
                    f'no message on {found.name} within {args.timeout:g} s '
                    f'({publishers} publisher(s) on the graph)'
                )
                break
    print(echo.summary(found.name), file=sys.stderr)  # noqa: T201
    if timed_out:
        print(f'slam_echo: error: {timed_out}', file=sys.stderr)  # noqa: T201
        return EXIT_TIMEOUT
    return 0


if __name__ == '__main__':
    sys.exit(main())
