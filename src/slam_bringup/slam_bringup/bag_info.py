"""bag_info: print a bag's topics, types, message counts, QoS and duration."""

from __future__ import annotations

import argparse
import sys
from datetime import UTC, datetime

from slam_core.cli import console_main
from slam_ros.bag.source import BagSource, TopicSummary


def _qos_text(topic: TopicSummary) -> str:
    if not topic.offered_qos:
        return 'latched' if topic.latched else '-'
    profile = topic.offered_qos[0]
    return f'{profile.reliability.name.lower()}/{profile.durability.name.lower()}'


def describe(source: BagSource) -> str:
    """Return the human-readable summary of an open bag."""
    start = datetime.fromtimestamp(source.start_ns / 1e9, tz=UTC).isoformat()
    lines = [
        f'Path:       {source.path}',
        f'Storage:    {source.storage}',
        f'Duration:   {source.duration_ns / 1e9:.3f} s',
        f'Start:      {start} ({source.start_ns} ns)',
        f'Messages:   {source.message_count}',
        'Topics:',
    ]
    topics = sorted(source.topics().values(), key=lambda t: t.name)
    width = max((len(t.name) for t in topics), default=5)
    type_width = max((len(t.msgtype) for t in topics), default=4)
    for topic in topics:
        lines.append(
            f'  {topic.name:<{width}}  {topic.msgtype:<{type_width}}  '
            f'{topic.count:>8} msgs  {_qos_text(topic)}'
        )
    return '\n'.join(lines)


@console_main('bag_info')
def main(argv: list[str] | None = None) -> int:
    """Print the summary of each bag given."""
    parser = argparse.ArgumentParser(prog='bag_info', description=__doc__)
    parser.add_argument('bags', nargs='+', help='bag directory, .mcap, .db3 or ROS 1 .bag')
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    for index, path in enumerate(args.bags):
        with BagSource(path) as source:
            if index:
                print()  # noqa: T201
            print(describe(source))  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
