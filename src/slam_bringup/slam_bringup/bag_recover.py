"""bag_recover: rebuild a readable rosbag2 bag from a killed recorder or a damaged mcap.

OUTPUT defaults to NAME beside a staging directory .NAME.recording-PID, else INPUT_recovered."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from slam_core.cli import PlainDescriptionHelpFormatter, console_main
from slam_core.errors import BagError
from slam_ros.bag.recover import default_output, recover


def build_arg_parser() -> argparse.ArgumentParser:
    """Command-line options."""
    parser = argparse.ArgumentParser(
        prog='bag_recover',
        description=__doc__,
        formatter_class=PlainDescriptionHelpFormatter,
    )
    parser.add_argument('input', help='staging directory, rosbag2 directory or .mcap file')
    parser.add_argument('-o', '--output', help='bag directory to create (must not exist)')
    return parser


@console_main('bag_recover')
def main(argv: list[str] | None = None) -> int:
    """Recover one bag; exit 0 when a bag was written, 2 on bad input."""
    args = build_arg_parser().parse_args(sys.argv[1:] if argv is None else argv)
    source = Path(args.input)
    output = Path(args.output) if args.output else default_output(source)
    if output.exists():
        raise BagError(f'output {str(output)!r} exists already; choose another with -o')
    report = recover(source, output)
    lines = [
        f'recovered {report.message_count} messages from {report.chunks} chunks of '
        f'{str(source)!r} into {str(output)!r}'
    ]
    lines += [f'  {topic}: {count}' for topic, count in sorted(report.counts.items())]
    if report.complete:
        lines.append('dropped: nothing (the data section was complete)')
    lines += [f'dropped: {what}' for what in report.dropped]
    print('\n'.join(lines))  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
