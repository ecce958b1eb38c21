"""bag_player: replay a ROS 2 (mcap, sqlite3) or ROS 1 bag onto live topics.

Topics: publishes the played topics (recorded QoS), /clock, /slam/end_of_input, /diagnostics.
Frames: none. In full: docs/design/bringup_nodes.md."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Empty

from slam_bringup.pacing import PacedGate
from slam_core.cli import (
    PlainDescriptionHelpFormatter,
    add_print_config,
    console_main,
    without_parameter_section,
)
from slam_core.errors import ParameterError, SlamError
from slam_core.params import NON_NEGATIVE, POSITIVE, Param, ParamTable, ParamType
from slam_core.progress import ProgressReporter
from slam_ros.bag.playback import LatenessStats, PlaybackConfig, Prefetcher, TimeMapping
from slam_ros.bag.source import BagSource
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import check_parameter_files, declare_parameters, parse_remaps, remap_rule
from slam_ros.progress import END_QOS, END_TOPIC, PROGRESS_QOS, PROGRESS_TOPIC
from slam_ros.qos import profile_from_recorded, replayed_qos
from slam_ros.typesys import message_class

PARAMETERS = ParamTable(
    'bag_player',
    (
        Param('bag_path', '', 'bag directory, .mcap, .db3 or ROS 1 .bag to play (required)'),
        Param('rate', 1.0, 'playback speed factor', range=POSITIVE),
        Param(
            'start_offset_s',
            0.0,
            'seconds to skip from the start of the bag, s',
            range=NON_NEGATIVE,
        ),
        Param(
            'topics',
            [],
            'recorded topics to play; empty plays all',
            type=ParamType.STRING_ARRAY,
        ),
        Param(
            'remap',
            [],
            "topic renames 'recorded:=published'",
            type=ParamType.STRING_ARRAY,
            validator=remap_rule,
        ),
        Param(
            'replayable_topics',
            [],
            'played topics published transient-local (late joiners get the last 1000)',
            type=ParamType.STRING_ARRAY,
        ),
        Param('loop', False, 'start over when the bag ends'),
        Param(
            'clock_hz',
            100.0,
            'rate of /clock messages, Hz; 0 disables /clock',
            range=NON_NEGATIVE,
        ),
        Param(
            'wait_for_subscribers_s',
            0.0,
            'wait up to this long for every played topic to have a subscriber, s; 0 starts '
            'at once',
            range=NON_NEGATIVE,
        ),
        Param(
            'progress_period_s',
            5.0,
            'period of progress log lines off a terminal, s',
            range=POSITIVE,
        ),
        Param('paced', False, 'paced replay: each message once the graph is done with the last'),
        Param(
            'paced_nodes',
            [],
            'paced: the nodes whose first progress report playback waits for',
            type=ParamType.STRING_ARRAY,
        ),
        Param(
            'paced_timeout_s',
            60.0,
            'paced: longest wait for the graph before playing on (with a warning), s',
            range=POSITIVE,
        ),
    ),
)

REPLAYABLE_DEPTH = 1000  # as odometry_increments: 1764 observations of 233 s is 7.6 Hz
CLOCK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
WAIT_POLL_S = 0.01
SUBSCRIBER_SETTLE_S = 1.0  # after wait_for_subscribers_s: the readers' side of discovery
PACED_POLL_S = 0.05  # paced: the wait wakes on each progress report, at the latest this often
PRIME_TIMEOUT_S = 2.0
PROGRESS_TICK_S = 0.1
FINAL_REPORT_S = 0.25


def config_from_parameters(values: dict[str, Any]) -> PlaybackConfig:
    """Validate parameter values into a PlaybackConfig (raises ParameterError)."""
    checked = PARAMETERS.validate(values)
    bag_path = str(checked['bag_path'])
    if not bag_path:
        raise PARAMETERS.fail('bag_path', bag_path, 'is required: the bag to play')
    return PlaybackConfig(
        bag_path=Path(bag_path).expanduser(),
        rate=checked['rate'],
        start_offset_s=checked['start_offset_s'],
        topics=tuple(checked['topics']),
        remaps=parse_remaps('remap', checked['remap']),
        loop=checked['loop'],
        clock_hz=checked['clock_hz'],
        wait_for_subscribers_s=checked['wait_for_subscribers_s'],
        progress_period_s=checked['progress_period_s'],
    )


class BagPlayerNode(Node):
    """Replays a bag in a background thread; ``finished`` is set when it is done."""

    def __init__(self, **kwargs: object) -> None:
        super().__init__('bag_player', **kwargs)  # type: ignore[arg-type]
        values = declare_parameters(self, PARAMETERS)
        self.config = config_from_parameters(values)
        self.paced = bool(values['paced'])
        self.paced_timeout_s = float(values['paced_timeout_s'])
        self.paced_timeouts = 0
        self.gate = PacedGate(name for name in values['paced_nodes'] if name)  # [''] = none
        self._progress = threading.Event()  # set by each progress report (paced)
        self.end_publisher = self.create_publisher(Empty, END_TOPIC, END_QOS)
        if self.paced:
            self.create_subscription(
                DiagnosticStatus, PROGRESS_TOPIC, self._on_progress, PROGRESS_QOS
            )
        self.source = BagSource(self.config.bag_path).__enter__()
        span_s = max(self.source.end_ns - self.source.start_ns, 0) / 1e9
        if self.config.start_offset_s > span_s:
            self.source.__exit__(None, None, None)
            raise ParameterError(
                f'parameter start_offset_s={self.config.start_offset_s:g}: beyond the end of '
                f'bag {str(self.config.bag_path)!r}, which spans {span_s:.3f} s'
            )
        self.topics = self._select_topics()
        replayable = {topic for topic in values['replayable_topics'] if topic}
        if replayable - set(self.topics):
            raise ParameterError(
                f'parameter replayable_topics: {sorted(replayable - set(self.topics))} '
                f'are not played (played: {", ".join(self.topics)})'
            )
        self.publishers_by_topic: dict[str, Publisher] = {}
        for name in self.topics:
            summary = self.source.topics()[name]
            cls = message_class(summary.msgtype, topic=name)
            qos = profile_from_recorded(summary.offered_qos, latched=summary.latched)
            if name in replayable:
                qos = replayed_qos(REPLAYABLE_DEPTH)
            published = self.config.remaps.get(name, name)
            self.publishers_by_topic[name] = self.create_publisher(cls, published, qos)
        self.clock_publisher = (
            self.create_publisher(Clock, '/clock', CLOCK_QOS) if self.config.clock_hz > 0 else None
        )
        self.lateness = LatenessStats()
        self.published = 0
        # keys made here: the playback thread only increments them while reports read them
        self.published_by_topic = dict.fromkeys(self.topics, 0)
        self.skipped = 0
        self._lateness_reported = 0
        self.diagnostics = Diagnostics(self, self._counts, values=self._lateness_values)
        self._position_ns = self._pass_start_ns = self.source.start_ns
        on_terminal = sys.stderr.isatty()
        self.progress = ProgressReporter(
            max(self.source.end_ns - self.source.start_ns, 0) / 1e9 - self.config.start_offset_s,
            label=f'bag_player {self.config.bag_path.name}',
            unit='s',
            stream=sys.stderr if on_terminal else None,
            log=None if on_terminal else self.get_logger().info,
            period_s=self.config.progress_period_s,
        )
        self._progress_closed = False
        self.create_timer(
            PROGRESS_TICK_S if on_terminal else self.config.progress_period_s,
            self.report_progress,
            clock=RosClock(clock_type=ClockType.STEADY_TIME),
        )
        self.error: SlamError | None = None
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._play_safely, name='bag-player', daemon=True)
        self._thread.start()

    def _on_progress(self, status: DiagnosticStatus) -> None:
        if status.name != self.get_fully_qualified_name():  # its own publishes are counted
            self.gate.update(status.name, [(value.key, value.value) for value in status.values])
            self._progress.set()

    def _select_topics(self) -> tuple[str, ...]:
        recorded = self.source.topics()
        if not self.config.topics:
            return tuple(sorted(recorded))
        for topic in self.config.topics:
            if topic not in recorded:
                raise ParameterError(
                    f'parameter topics: topic {topic!r} is not in bag '
                    f'{str(self.config.bag_path)!r} (it has: {", ".join(sorted(recorded))})'
                )
        return self.config.topics

    # -- playback thread ------------------------------------------------------------------
    def _play_safely(self) -> None:
        try:
            self._wait_for_subscribers()
            while not self._stop.is_set():
                if self.paced:
                    self._play_paced()  # says the end itself, once the graph is done
                else:
                    self._play_once()
                if not self.config.loop:
                    if not self.paced and not self._stop.is_set():
                        self.end_publisher.publish(Empty())
                    break
        except SlamError as err:
            self.error = err  # reported by whoever runs the node (CLI or graph runner)
        finally:
            self.finished.set()

    def _counts(self) -> dict[str, int]:
        """The counts on /diagnostics: messages published per topic, skipped."""
        counts = {
            f'published {self.config.remaps.get(name, name)}': count
            for name, count in self.published_by_topic.items()
        }
        counts['skipped'] = self.skipped
        if self.paced:
            counts['paced timeouts'] = self.paced_timeouts
        return counts

    def _lateness_values(self) -> dict[str, str]:
        """The lateness on /diagnostics, of the messages published since the last report."""
        window = self.lateness.samples_ns[self._lateness_reported :]
        self._lateness_reported += len(window)
        window.sort()
        median = f'{window[len(window) // 2] / 1e6:.2f}' if window else 'nan'
        maximum = f'{window[-1] / 1e6:.2f}' if window else 'nan'
        return {'lateness ms median': median, 'lateness ms max': maximum}

    def _wait_for_subscribers(self) -> None:
        deadline = time.monotonic() + self.config.wait_for_subscribers_s
        waiting = list(self.publishers_by_topic.values())
        while waiting and time.monotonic() < deadline and not self._stop.is_set():
            waiting = [p for p in waiting if p.get_subscription_count() == 0]
            if waiting:
                self._stop.wait(WAIT_POLL_S)
        if waiting and self.config.wait_for_subscribers_s > 0:
            names = ', '.join(p.topic_name for p in waiting)
            self.get_logger().warning(f'starting without subscribers on: {names}')
        elif self.config.wait_for_subscribers_s > 0:
            # The player's writers have matched their readers; the readers match the writers
            # on their side up to a discovery exchange later, and until then a best-effort
            # reader drops what it gets and a transient-local one gets the history late.
            self._stop.wait(SUBSCRIBER_SETTLE_S)

    def _play_once(self) -> None:
        config = self.config
        bag_start = self.source.start_ns + round(config.start_offset_s * 1e9)
        self._pass_start_ns = bag_start
        clock_period_ns = round(1e9 / config.clock_hz) if self.clock_publisher else 0
        prefetch = Prefetcher(self.source, self.topics, bag_start)
        # Start the wall clock from a warm buffer: the first seconds of reading and decoding
        # would otherwise compete with publishing for the GIL.
        prefetch.wait_primed(PRIME_TIMEOUT_S)
        mapping = TimeMapping(bag_start, time.monotonic_ns(), config.rate)
        next_clock_ns = mapping.wall_start_ns
        published_before = self.published
        try:
            for message in prefetch:
                deadline = mapping.wall_deadline_ns(message.timestamp_ns)
                next_clock_ns = self._sleep_until(
                    deadline, mapping, next_clock_ns, clock_period_ns
                )
                if self._stop.is_set():
                    return
                self.publishers_by_topic[message.topic].publish(message.data)
                self.lateness.add(time.monotonic_ns() - deadline)
                self.published += 1
                self.published_by_topic[message.topic] += 1
                self._position_ns = message.timestamp_ns
        finally:
            prefetch.close()
        in_bag = sum(self.source.topics()[name].count for name in self.topics)
        self.skipped += max(in_bag - (self.published - published_before), 0)

    def _play_paced(self) -> None:
        """One pass without timing: each message once the graph is done (``pacing``)."""
        bag_start = self.source.start_ns + round(self.config.start_offset_s * 1e9)
        self._pass_start_ns = bag_start
        published_before = self.published
        by_topic = {name: p.topic_name for name, p in self.publishers_by_topic.items()}
        played: dict[str, int] = dict.fromkeys(by_topic.values(), 0)
        self._wait_for_graph(played, first=True)
        prefetch = Prefetcher(self.source, self.topics, bag_start)
        try:
            for message in prefetch:
                self._wait_for_graph(played)
                if self._stop.is_set():
                    return
                if self.clock_publisher is not None:
                    self._publish_clock(message.timestamp_ns)
                self.publishers_by_topic[message.topic].publish(message.data)
                played[by_topic[message.topic]] += 1
                self.published += 1
                self.published_by_topic[message.topic] += 1
                self._position_ns = message.timestamp_ns
            self._wait_for_graph(played)
            # what the nodes hold back until their inputs end comes out now (progress.py)
            self.end_publisher.publish(Empty())
            end = self.end_publisher.topic_name
            played[end] = played.get(end, 0) + 1
            self._wait_for_graph(played)
        finally:
            prefetch.close()
        in_bag = sum(self.source.topics()[name].count for name in self.topics)
        self.skipped += max(in_bag - (self.published - published_before), 0)

    def _wait_for_graph(self, played: dict[str, int], *, first: bool = False) -> None:
        """Wait up to paced_timeout_s (then warn) for the graph to be done with ``played``."""
        deadline = time.monotonic() + self.paced_timeout_s
        while not self._stop.is_set():
            waiting: list[object] = []
            if first:
                matched = {p.topic_name: p.get_subscription_count() for p in self.publishers}
                waiting = [*self.gate.missing(), *self.gate.unmatched(matched)]
            if not waiting:
                waiting = list(self.gate.shortfalls(played))
            if not waiting:
                return
            if time.monotonic() >= deadline:
                self.paced_timeouts += 1
                what = 'before the first message, ' if first else ''
                listed = '; '.join(map(str, waiting[:3]))
                self.get_logger().warning(
                    f'paced replay: {what}still waiting for {listed} after '
                    f'{self.paced_timeout_s:g} s; playing on ({self.paced_timeouts} so far)'
                )
                return
            self._progress.wait(PACED_POLL_S)
            self._progress.clear()

    def _sleep_until(
        self, deadline_ns: int, mapping: TimeMapping, next_clock_ns: int, clock_period_ns: int
    ) -> int:
        """Sleep until ``deadline_ns``, publishing /clock on its period; return next tick."""
        while not self._stop.is_set():
            now = time.monotonic_ns()
            if clock_period_ns and now >= next_clock_ns:
                self._publish_clock(mapping.bag_time_ns(min(now, deadline_ns)))
                next_clock_ns += clock_period_ns
                if next_clock_ns <= now:  # after a stall: one tick now, not a burst
                    next_clock_ns = now + clock_period_ns
                continue
            if now >= deadline_ns:
                break
            wake = min(deadline_ns, next_clock_ns) if clock_period_ns else deadline_ns
            self._stop.wait(max(wake - now, 0) / 1e9)
        return next_clock_ns

    def report_progress(self) -> None:
        """Timer callback: progress is drawn here, never in the timing-critical thread."""
        if self._progress_closed:
            return
        done_s = max(self._position_ns - self._pass_start_ns, 0) / 1e9
        self.progress.update(done_s, items=self.published)
        if self.finished.is_set():
            self.progress.finish()
            self._progress_closed = True

    def _publish_clock(self, bag_ns: int) -> None:
        assert self.clock_publisher is not None
        message = Clock()
        message.clock.sec, message.clock.nanosec = divmod(bag_ns, 1_000_000_000)
        self.clock_publisher.publish(message)

    def stop(self) -> None:
        """Stop playback and wait for the playback thread."""
        self._stop.set()
        self._thread.join(timeout=5.0)

    def destroy_node(self) -> None:
        self.stop()
        self.source.__exit__(None, None, None)
        super().destroy_node()

    def summary(self) -> str:
        """Return a one-line summary of the playback so far."""
        played = f'published {self.published} messages from {str(self.config.bag_path)!r}'
        if not self.published:
            return f'{played} (nothing to publish: check topics and start_offset_s)'
        if self.paced:
            return f'{played}, paced ({self.paced_timeouts} waits for the graph timed out)'
        late = self.lateness.summary_ms()
        return f'{played}; lateness median {late["median_ms"]:.2f} ms, p95 {late["p95_ms"]:.2f} ms'


def build_arg_parser() -> argparse.ArgumentParser:
    """Command-line options; each maps onto a node parameter."""
    parser = argparse.ArgumentParser(
        prog='bag_player',
        description=without_parameter_section(__doc__ or ''),
        epilog=PARAMETERS.render() + '\n\nROS arguments (--ros-args ...) are accepted too.',
        formatter_class=PlainDescriptionHelpFormatter,
    )
    add_print_config(parser, PARAMETERS)
    parser.add_argument('bag', nargs='?', help='bag directory, .mcap, .db3 or .bag file')
    parser.add_argument('-r', '--rate', type=float, help='speed factor (default 1.0)')
    parser.add_argument('-s', '--start-offset', type=float, help='seconds to skip')
    parser.add_argument('--topics', nargs='+', help='recorded topics to play (default all)')
    parser.add_argument(
        '--remap', nargs='+', metavar='FROM:=TO', help='rename recorded topics when publishing'
    )
    parser.add_argument('-l', '--loop', action='store_true', default=None, help='loop forever')
    parser.add_argument('--clock-hz', type=float, help='/clock rate in Hz, 0 disables it')
    parser.add_argument(
        '--wait-for-subscribers',
        type=float,
        metavar='S',
        help='wait up to S seconds for subscribers on every topic before starting',
    )
    parser.add_argument(
        '--paced',
        action='store_true',
        default=None,
        help='paced replay: each message once the nodes reporting progress are done',
    )
    return parser


def overrides_from_args(args: argparse.Namespace) -> list[rclpy.parameter.Parameter]:
    """Turn given command-line options into parameter overrides."""
    mapping = {
        'bag_path': args.bag,
        'rate': args.rate,
        'start_offset_s': args.start_offset,
        'topics': args.topics,
        'remap': args.remap,
        'loop': args.loop,
        'clock_hz': args.clock_hz,
        'wait_for_subscribers_s': args.wait_for_subscribers,
        'paced': args.paced,
    }
    return [
        rclpy.parameter.Parameter(name, value=value)
        for name, value in mapping.items()
        if value is not None
    ]


@console_main('bag_player')
def main(argv: list[str] | None = None) -> int:
    """Play a bag until it ends (or forever with --loop); exit 0 when it played fully."""
    argv = sys.argv[1:] if argv is None else argv
    ros_args = rclpy.utilities.remove_ros_args(['bag_player', *argv])[1:]
    args = build_arg_parser().parse_args(ros_args)
    check_parameter_files(argv, PARAMETERS)
    # Ctrl-C and SIGTERM stop the playback; the context stays valid for the last words
    stop = threading.Event()
    rclpy.init(args=['bag_player', *argv], signal_handler_options=SignalHandlerOptions.NO)
    previous = {
        s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)
    }
    node = None
    try:
        node = BagPlayerNode(parameter_overrides=overrides_from_args(args))
        while rclpy.ok() and not node.finished.is_set() and not stop.is_set():
            rclpy.spin_once(node, timeout_sec=0.1)
        if node.error is not None:
            raise node.error
        node.report_progress()
        stopped = stop.is_set() and not node.finished.is_set()
        node.get_logger().info(('stopped: ' if stopped else '') + node.summary())
        node.diagnostics.publish()  # the final counts
        time.sleep(FINAL_REPORT_S)  # on their way (reliable) before the process ends
        return 130 if stopped else 0
    except (KeyboardInterrupt, ExternalShutdownException):
        return 130
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
