"""bag_recorder: record live topics into an mcap bag (rosbag2 format, readable by ros2 bag).

Topics: subscribes ``topics`` (or all but ``exclude``), raw CDR; publishes /diagnostics.
Ctrl-C or SIGTERM finalizes the bag. In full: docs/design/bringup_nodes.md."""

from __future__ import annotations

import argparse
import functools
import signal
import sys
import threading
import time
from datetime import datetime
from pathlib import Path
from types import FrameType

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.executors import Executor, ExternalShutdownException
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from slam_core.cli import (
    PlainDescriptionHelpFormatter,
    add_print_config,
    console_main,
    without_parameter_section,
)
from slam_core.errors import SlamError
from slam_core.params import AT_LEAST_ONE, POSITIVE, Param, ParamTable, ParamType
from slam_ros.bag.recording import AtomicBagWriter
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import check_parameter_files, declare_parameters
from slam_ros.qos import matching_qos, recorded_from_profile
from slam_ros.spin import TakeSafeExecutor
from slam_ros.typesys import TypeRegistry, message_class

PARAMETERS = ParamTable(
    'bag_recorder',
    (
        Param('output', '', 'bag directory to create (default rosbag2_<date>_<time>)'),
        Param(
            'topics',
            [],
            'topics to record; empty records every topic',
            type=ParamType.STRING_ARRAY,
        ),
        Param(
            'exclude',
            ['/rosout', '/parameter_events'],
            'topics skipped when recording all topics',
        ),
        Param(
            'discovery_period_s',
            0.5,
            'period of the search for new topics, s',
            range=POSITIVE,
        ),
        Param('queue_depth', 1000, 'subscription history depth', range=AT_LEAST_ONE),
        Param(
            'flush_period_s',
            1.0,
            'longest time a received message waits in memory before it is on disk, s',
            range=POSITIVE,
        ),
    ),
)
DRAIN_TIMEOUT_S = 2.0
FINAL_REPORT_S = 0.25


def default_output_name() -> str:
    """Return rosbag2's default bag name for now."""
    return datetime.now().strftime('rosbag2_%Y_%m_%d-%H_%M_%S')


class BagRecorderNode(Node):
    """Records topics into an AtomicBagWriter; ``finalize()`` closes the bag."""

    def __init__(self, **kwargs: object) -> None:
        super().__init__('bag_recorder', **kwargs)  # type: ignore[arg-type]
        values = declare_parameters(self, PARAMETERS)
        self.discovery_period_s = float(values['discovery_period_s'])
        self.queue_depth = int(values['queue_depth'])
        self.selected = tuple(values['topics'])
        self.exclude = frozenset(values['exclude'])
        self.writer = AtomicBagWriter(
            Path(values['output'] or default_output_name()),
            flush_period_s=float(values['flush_period_s']),
        )
        self.types = TypeRegistry()
        self._unavailable: dict[str, str] = {}
        self._lock = threading.Lock()
        self.dropped = 0
        self.diagnostics = Diagnostics(self, self._counts)
        self.get_logger().info(
            f'recording {", ".join(self.selected) or "all topics"} to '
            f'{str(self.writer.target)!r} (staged in {str(self.writer.staging)!r})'
        )
        self._discover()
        # Steady clock: with use_sim_time a ROS-time timer would wait for /clock to move.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(self.discovery_period_s, self._discover, clock=steady)
        # Half the period: a chunk is written at most flush_period_s after its first message.
        self.create_timer(self.writer.flush_period_s / 2, self._flush, clock=steady)

    def _counts(self) -> dict[str, int]:
        """The counts on /diagnostics: messages written per topic; dropped after closing."""
        counts = {f'written {topic}': n for topic, n in sorted(self.writer.counts.items())}
        counts['dropped'] = self.dropped
        return counts

    def _wanted(self, topic: str) -> bool:
        if self.selected:
            return topic in self.selected
        return topic not in self.exclude

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if not self._wanted(topic) or self.writer.has_topic(topic) or self.writer.closed:
                continue
            if len(types) > 1:
                self.get_logger().warning(
                    f'topic {topic!r} has several types {types}; recording {types[0]!r}'
                )
            try:
                self._subscribe(topic, types[0])
            except SlamError as err:
                if self._unavailable.get(topic) != str(err):
                    self._unavailable[topic] = str(err)
                    self.get_logger().error(f'not recording {topic!r}: {err}')

    def _subscribe(self, topic: str, msgtype: str) -> None:
        cls = message_class(msgtype, topic=topic)
        msgdef, rihs01 = self.types.msgdef_and_hash(msgtype)
        publishers = self.get_publishers_info_by_topic(topic)
        offered = [info.qos_profile for info in publishers]
        self.writer.add_topic(
            topic,
            msgtype,
            msgdef=msgdef,
            rihs01=rihs01,
            offered_qos=[recorded_from_profile(q) for q in offered],
        )
        qos = matching_qos(offered, self.queue_depth)
        on_message = self.diagnostics.timed(functools.partial(self._on_message, topic), topic)
        self.create_subscription(cls, topic, on_message, qos, raw=True)
        self.get_logger().info(f'recording {topic!r} ({msgtype})')

    def _on_message(self, topic: str, data: bytes) -> None:
        with self._lock:
            if self.writer.closed:
                self.dropped += 1
            else:
                self.writer.write(topic, self.get_clock().now().nanoseconds, data)

    def _flush(self) -> None:
        with self._lock:
            self.writer.flush()

    def finalize(self) -> Path:
        """Close the bag and move it to its output path; return that path."""
        with self._lock:
            path = self.writer.close()
        counts = ', '.join(f'{t}: {n}' for t, n in sorted(self.writer.counts.items()))
        self.get_logger().info(
            f'wrote {self.writer.message_count} messages to {str(path)!r} ({counts or "none"})'
        )
        return path

    def destroy_node(self) -> None:
        if not self.writer.closed:
            self.finalize()
        super().destroy_node()


def drain(executor: Executor, node: BagRecorderNode, timeout_s: float) -> None:
    """Execute callbacks until no new message arrives for one poll, or until timeout."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        before = node.writer.message_count
        executor.spin_once(timeout_sec=0.05)
        if node.writer.message_count == before:
            return


def build_arg_parser() -> argparse.ArgumentParser:
    """Command-line options; each maps onto a node parameter."""
    parser = argparse.ArgumentParser(
        prog='bag_recorder',
        description=without_parameter_section(__doc__ or ''),
        epilog=PARAMETERS.render() + '\n\nROS arguments (--ros-args ...) are accepted too.',
        formatter_class=PlainDescriptionHelpFormatter,
    )
    add_print_config(parser, PARAMETERS)
    parser.add_argument('topics', nargs='*', help='topics to record (with -a: all)')
    parser.add_argument('-a', '--all', action='store_true', help='record every topic')
    parser.add_argument('-o', '--output', help='bag directory to create')
    parser.add_argument('--exclude', nargs='+', help='topics to skip with --all')
    return parser


@console_main('bag_recorder')
def main(argv: list[str] | None = None) -> int:
    """Record until Ctrl-C or SIGTERM, then finalize the bag; exit 0 when it was written."""
    argv = sys.argv[1:] if argv is None else argv
    args = build_arg_parser().parse_args(rclpy.utilities.remove_ros_args(['x', *argv])[1:])
    if bool(args.topics) == bool(args.all):
        print('bag_recorder: error: give topics to record, or --all', file=sys.stderr)  # noqa: T201
        return 2
    overrides = (
        [rclpy.parameter.Parameter('topics', value=list(args.topics))] if args.topics else []
    )
    if args.output:
        overrides.append(rclpy.parameter.Parameter('output', value=args.output))
    if args.exclude:
        overrides.append(rclpy.parameter.Parameter('exclude', value=list(args.exclude)))

    stop = threading.Event()

    def request_stop(signum: int, frame: FrameType | None) -> None:
        stop.set()

    check_parameter_files(argv, PARAMETERS)
    rclpy.init(args=['bag_recorder', *argv], signal_handler_options=SignalHandlerOptions.NO)
    previous = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    executor = TakeSafeExecutor()  # a message rclpy fails to take is counted, not fatal
    node = None
    try:
        node = BagRecorderNode(parameter_overrides=overrides)
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
        drain(executor, node, DRAIN_TIMEOUT_S)
        node.finalize()
        node.diagnostics.publish()  # the final counts
        time.sleep(FINAL_REPORT_S)  # on their way (reliable) before the process ends
        return 0
    except ExternalShutdownException:
        return 130
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if node is not None:
            executor.remove_node(node)
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
