"""Benchmark: bag_player publish lateness at rate 1.0, side by side with a naive replay loop.

Writes a bag (mcap, ``--duration`` seconds) with 30 Hz ``sensor_msgs/msg/Image`` (640x480
rgb8, random bytes from a seeded numpy Generator) and 50 Hz ``nav_msgs/msg/Odometry``, starts a
subscriber node in a separate process on every played topic, then replays the bag twice in this
process over real DDS (the loopback profile of ``scripts/env.sh``):

1. reference: a naive loop that reads the bag with rosbags and publishes the raw CDR with plain
   rclpy publishers, sleeping ``time.sleep(deadline - now)``; no prefetch, no /clock;
2. ours: ``slam_bringup.bag_player.BagPlayerNode`` with its default settings (prefetch thread,
   /clock at 100 Hz), its node spun in the main thread as its ``main()`` does.

Publish lateness of a message is the monotonic time at which ``publish()`` returned minus its
scheduled time (the first message's ready time plus its bag offset divided by the rate). The
subscriber process reports, per topic, the inter-arrival jitter ``|interval - nominal period|``.

The Markdown table is printed and written to ``--output``. Acceptance (project rule): the
median publish lateness of ours is below 5 ms at rate 1.0; the exit status is 1 when it is not.

Run (after ``bash scripts/bootstrap.sh``)::

    source scripts/env.sh
    python bench/bag_player_lateness.py [--duration 20] [--seed 0] [--output FILE]
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import json
import math
import os
import platform
import resource
import select
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rclpy
from bench_common import source_revision
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rosbags.interfaces import (
    Qos,
)
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from slam_bringup.bag_player import BagPlayerNode
from slam_core.geometry.quaternion import quaternion_from_yaw
from slam_ros.bag.playback import LatenessStats
from slam_ros.qos import output_qos, recorded_from_profile
from slam_ros.typesys import message_class

BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / 'results' / 'bag_player_lateness.md'

IMAGE_TOPIC = '/camera/image_raw'
ODOM_TOPIC = '/odom'
IMAGE_TYPE = 'sensor_msgs/msg/Image'
ODOM_TYPE = 'nav_msgs/msg/Odometry'
IMAGE_HZ = 30.0
ODOM_HZ = 50.0
IMAGE_WIDTH, IMAGE_HEIGHT = 640, 480
BAG_START_NS = 1_700_000_000 * 10**9
NOMINAL_PERIOD_NS = {IMAGE_TOPIC: round(1e9 / IMAGE_HZ), ODOM_TOPIC: round(1e9 / ODOM_HZ)}

SIDES = ('reference', 'ours')
SIDE_LABELS = {'reference': 'naive loop (reference)', 'ours': 'bag_player (ours)'}
ACCEPT_MEDIAN_MS = 5.0
WAIT_FOR_SUBSCRIBERS_S = 10.0
SUBSCRIBER_READY_TIMEOUT_S = 30.0
STARTUP_MESSAGES = 10  # the 'first 10' column: lateness right after the start
DRAIN_S = 1.0  # lets the subscriber take in the last messages before it is stopped
READY = 'READY'


# -- the bag ------------------------------------------------------------------------------
@dataclass(frozen=True)
class BagSpec:
    """What was written: message counts per topic, duration (float s) and size (bytes)."""

    path: Path
    counts: dict[str, int]
    duration_s: float
    size_bytes: int


def recorded_qos() -> Qos:
    """Reliable, volatile, keep last 10: what a typical sensor driver offers."""
    return recorded_from_profile(output_qos())


def _image(store: Typestore, stamp_ns: int, rng: np.random.Generator) -> object:
    types = store.types
    sec, nanosec = divmod(stamp_ns, 10**9)
    header = types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec),
        frame_id='camera_optical_frame',
    )
    size = IMAGE_WIDTH * IMAGE_HEIGHT * 3
    return types[IMAGE_TYPE](
        header=header,
        height=IMAGE_HEIGHT,
        width=IMAGE_WIDTH,
        encoding='rgb8',
        is_bigendian=0,
        step=IMAGE_WIDTH * 3,
        data=np.frombuffer(rng.bytes(size), dtype=np.uint8),
    )


def _odometry(store: Typestore, stamp_ns: int) -> object:
    """Odometry of a robot on a 2 m circle at 0.5 m/s, in the odom frame."""
    types = store.types
    sec, nanosec = divmod(stamp_ns, 10**9)
    t_s = (stamp_ns - BAG_START_NS) / 1e9
    speed_mps, radius_m = 0.5, 2.0
    yaw_rad = speed_mps / radius_m * t_s
    qx, qy, qz, qw = quaternion_from_yaw(yaw_rad)
    point = types['geometry_msgs/msg/Point']
    vector = types['geometry_msgs/msg/Vector3']
    pose = types['geometry_msgs/msg/Pose'](
        position=point(
            x=radius_m * math.sin(yaw_rad), y=radius_m * (1 - math.cos(yaw_rad)), z=0.0
        ),
        orientation=types['geometry_msgs/msg/Quaternion'](x=qx, y=qy, z=qz, w=qw),
    )
    twist = types['geometry_msgs/msg/Twist'](
        linear=vector(x=speed_mps, y=0.0, z=0.0),
        angular=vector(x=0.0, y=0.0, z=speed_mps / radius_m),
    )
    covariance = np.diag([0.01, 0.01, 1e6, 1e6, 1e6, 0.02]).reshape(36)
    return types[ODOM_TYPE](
        header=types['std_msgs/msg/Header'](
            stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec),
            frame_id='odom',
        ),
        child_frame_id='base_link',
        pose=types['geometry_msgs/msg/PoseWithCovariance'](pose=pose, covariance=covariance),
        twist=types['geometry_msgs/msg/TwistWithCovariance'](twist=twist, covariance=covariance),
    )


def write_bag(path: Path, *, duration_s: float, seed: int) -> BagSpec:
    """Write the benchmark bag (mcap rosbag2 directory) at ``path``; stamps are int ns."""
    store = get_typestore(Stores.ROS2_JAZZY)
    rng = np.random.default_rng(seed)
    events = [
        (BAG_START_NS + round(i * 1e9 / IMAGE_HZ), IMAGE_TOPIC)
        for i in range(round(duration_s * IMAGE_HZ))
    ]
    events += [
        (BAG_START_NS + round(i * 1e9 / ODOM_HZ), ODOM_TOPIC)
        for i in range(round(duration_s * ODOM_HZ))
    ]
    events.sort()
    counts = {IMAGE_TOPIC: 0, ODOM_TOPIC: 0}
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {
            topic: writer.add_connection(
                topic, msgtype, typestore=store, offered_qos_profiles=[recorded_qos()]
            )
            for topic, msgtype in ((IMAGE_TOPIC, IMAGE_TYPE), (ODOM_TOPIC, ODOM_TYPE))
        }
        for stamp_ns, topic in events:
            if topic == IMAGE_TOPIC:
                data = store.serialize_cdr(_image(store, stamp_ns, rng), IMAGE_TYPE)
            else:
                data = store.serialize_cdr(_odometry(store, stamp_ns), ODOM_TYPE)
            writer.write(connections[topic], stamp_ns, data)
            counts[topic] += 1
    size = sum(p.stat().st_size for p in path.rglob('*') if p.is_file())
    return BagSpec(path, counts, (events[-1][0] - events[0][0]) / 1e9, size)


# -- the subscriber process ---------------------------------------------------------------
def run_subscriber(subscriptions: list[str], output: Path, qos_name: str) -> int:
    """Subscriber process: record monotonic arrival times (int ns) per topic until stdin ends.

    ``subscriptions`` holds ``topic=pkg/msg/Type`` items. Arrival times go to ``output``
    as JSON when the parent closes this process's stdin.
    """
    qos = (
        qos_profile_sensor_data
        if qos_name == 'sensor'
        else QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    )
    rclpy.init()
    node = rclpy.create_node('bench_lateness_subscriber')
    arrivals: dict[str, list[int]] = {}
    for item in subscriptions:
        topic, msgtype = item.split('=', 1)
        arrivals[topic] = []
        node.create_subscription(
            message_class(msgtype, topic=topic), topic, _arrival_recorder(arrivals[topic]), qos
        )
    stop = threading.Event()
    threading.Thread(target=_set_at_eof, args=(stop,), daemon=True).start()
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    print(READY, flush=True)
    try:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
    finally:
        output.write_text(json.dumps(arrivals), encoding='utf-8')
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _set_at_eof(event: threading.Event) -> None:
    """Set ``event`` when stdin ends (the parent closed it, or died)."""
    sys.stdin.read()
    event.set()


def _arrival_recorder(arrivals: list[int]) -> Callable[[object], None]:
    def record(_message: object) -> None:
        arrivals.append(time.monotonic_ns())

    return record


class SubscriberProcess:
    """Starts ``run_subscriber`` in a child process; ``stop()`` returns its arrival times."""

    def __init__(self, topics: dict[str, str], output: Path, qos_name: str) -> None:
        self.output = output
        command = [
            sys.executable,
            str(Path(__file__).resolve()),
            '--subscriber',
            str(output),
            '--subscriber-qos',
            qos_name,
            *[f'--subscribe={topic}={msgtype}' for topic, msgtype in topics.items()],
        ]
        self.process = subprocess.Popen(
            command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        assert self.process.stdout is not None
        ready, _, _ = select.select([self.process.stdout], [], [], SUBSCRIBER_READY_TIMEOUT_S)
        line = self.process.stdout.readline().strip() if ready else ''
        if line != READY:
            self.close()
            raise RuntimeError(f'subscriber process did not start (got {line!r})')

    def stop(self) -> dict[str, list[int]]:
        """Stop the subscriber and return its arrival times per topic (int ns)."""
        assert self.process.stdin is not None
        self.process.stdin.close()
        self.process.wait(timeout=30.0)
        arrivals: dict[str, list[int]] = json.loads(self.output.read_text(encoding='utf-8'))
        return arrivals

    def close(self) -> None:
        """Kill the subscriber if it is still running."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10.0)


# -- the two replays ----------------------------------------------------------------------
@dataclass
class PhaseResult:
    """One replay: lateness samples (int ns), published count, wall and CPU seconds."""

    lateness_ns: list[int]
    published: int
    wall_s: float
    cpu_s: float
    peak_rss_mb: float


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def side_topic(side: str, topic: str) -> str:
    """Topic name that ``side`` publishes recorded ``topic`` on."""
    return f'/bench/{side}{topic}'


def run_reference(bag: Path) -> PhaseResult:
    """Naive replay: rosbags Reader, plain publishers, ``time.sleep(deadline - now)``."""
    qos = QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE
    )
    cpu0, wall0 = _cpu_s(), time.monotonic()
    node = rclpy.create_node('bench_reference_player')
    samples: list[int] = []
    try:
        with Reader(bag) as reader:
            publishers = {
                c.id: node.create_publisher(
                    message_class(c.msgtype), side_topic('reference', c.topic), qos
                )
                for c in reader.connections
            }
            deadline_s = time.monotonic() + WAIT_FOR_SUBSCRIBERS_S
            while time.monotonic() < deadline_s and any(
                p.get_subscription_count() == 0 for p in publishers.values()
            ):
                time.sleep(0.01)
            anchor: tuple[int, int] | None = None
            for connection, stamp_ns, raw in reader.messages():
                if anchor is None:
                    anchor = (stamp_ns, time.monotonic_ns())
                deadline_ns = anchor[1] + (stamp_ns - anchor[0])
                delay_ns = deadline_ns - time.monotonic_ns()
                if delay_ns > 0:
                    time.sleep(delay_ns / 1e9)
                publishers[connection.id].publish(bytes(raw))
                samples.append(time.monotonic_ns() - deadline_ns)
            return PhaseResult(
                samples, len(samples), time.monotonic() - wall0, _cpu_s() - cpu0, _peak_rss_mb()
            )
    finally:
        node.destroy_node()


def run_bag_player(bag: Path) -> PhaseResult:
    """Ours: BagPlayerNode with default settings, remapped to its side's topics."""
    remaps = [f'{t}:={side_topic("ours", t)}' for t in (IMAGE_TOPIC, ODOM_TOPIC)]
    overrides = [
        Parameter('bag_path', value=str(bag)),
        Parameter('rate', value=1.0),
        Parameter('remap', value=remaps),
        Parameter('wait_for_subscribers_s', value=WAIT_FOR_SUBSCRIBERS_S),
    ]
    cpu0, wall0 = _cpu_s(), time.monotonic()
    node = BagPlayerNode(parameter_overrides=overrides)
    try:
        while not node.finished.is_set():
            rclpy.spin_once(node, timeout_sec=0.1)
        if node.error is not None:
            raise node.error
        return PhaseResult(
            list(node.lateness.samples_ns),
            node.published,
            time.monotonic() - wall0,
            _cpu_s() - cpu0,
            _peak_rss_mb(),
        )
    finally:
        node.destroy_node()


# -- statistics and the report ------------------------------------------------------------
def summary_ms(samples_ns: Iterable[int]) -> dict[str, float]:
    """Count, median, p95 and max in ms, with the player's own definitions."""
    return LatenessStats(list(samples_ns)).summary_ms()


def jitter_ns(arrivals_ns: list[int], period_ns: int) -> list[int]:
    """Return ``|interval - period|`` of consecutive arrivals, int ns."""
    return [abs(b - a - period_ns) for a, b in itertools.pairwise(arrivals_ns)]


def _ratio(ours: float, reference: float) -> str:
    return f'{ours / reference:.2f}' if reference > 0 else 'n/a'


def render_report(
    spec: BagSpec,
    phases: dict[str, PhaseResult],
    arrivals: dict[str, list[int]],
    *,
    seed: int,
    subscriber_qos: str,
) -> tuple[str, bool]:
    """Return the Markdown report and whether the acceptance criterion passed."""
    late = {side: summary_ms(phases[side].lateness_ns) for side in SIDES}
    first = {side: summary_ms(phases[side].lateness_ns[:STARTUP_MESSAGES]) for side in SIDES}
    passed = late['ours']['median_ms'] < ACCEPT_MEDIAN_MS
    now = datetime.datetime.now(datetime.UTC).strftime('%Y-%m-%d %H:%M UTC')
    lines = [
        '# bag_player publish lateness at rate 1.0',
        '',
        f'{now}; {platform.platform()}, {os.cpu_count()} CPUs, Python '
        f'{platform.python_version()}, {os.environ.get("RMW_IMPLEMENTATION", "default rmw")}, '
        f'ROS_DOMAIN_ID {os.environ.get("ROS_DOMAIN_ID")}; code {source_revision()}.',
        f'Bag: mcap, {spec.duration_s:.1f} s, {spec.size_bytes / 1e6:.0f} MB, seed {seed}: '
        f'{spec.counts[IMAGE_TOPIC]} x {IMAGE_TYPE} {IMAGE_WIDTH}x{IMAGE_HEIGHT} rgb8 at '
        f'{IMAGE_HZ:g} Hz, {spec.counts[ODOM_TOPIC]} x {ODOM_TYPE} at {ODOM_HZ:g} Hz. '
        f'Subscriber: separate process, {subscriber_qos} QoS.',
        '',
        '## Publish lateness (publish() returned minus scheduled time), all messages',
        '',
        '| player | messages | median ms | p95 ms | max ms | max of first 10 ms | wall s | CPU s '
        '| peak RSS MB |',
        '|---|---:|---:|---:|---:|---:|---:|---:|---:|',
    ]
    for side in SIDES:
        stats, phase = late[side], phases[side]
        lines.append(
            f'| {SIDE_LABELS[side]} | {phase.published} | {stats["median_ms"]:.3f} | '
            f'{stats["p95_ms"]:.3f} | {stats["max_ms"]:.3f} | {first[side]["max_ms"]:.3f} | '
            f'{phase.wall_s:.1f} | '
            f'{phase.cpu_s:.1f} | {phase.peak_rss_mb:.0f} |'
        )
    ours, ref = late['ours'], late['reference']
    lines += [
        f'| ratio ours / reference | | {_ratio(ours["median_ms"], ref["median_ms"])} | '
        f'{_ratio(ours["p95_ms"], ref["p95_ms"])} | {_ratio(ours["max_ms"], ref["max_ms"])} | '
        f'{_ratio(first["ours"]["max_ms"], first["reference"]["max_ms"])} | '
        f'| {_ratio(phases["ours"].cpu_s, phases["reference"].cpu_s)} | |',
        '',
        'Wall and CPU time of this process run from node creation (bag opening, discovery wait '
        'and playback). Peak RSS is the process high-water mark at the end of each phase; the '
        'reference runs first.',
        '',
        '## Receive side: inter-arrival jitter |interval - nominal period| in the subscriber',
        '',
        '| topic | period ms | player | received / published | median ms | p95 ms | max ms |',
        '|---|---:|---|---:|---:|---:|---:|',
    ]
    for topic in (IMAGE_TOPIC, ODOM_TOPIC):
        period_ns = NOMINAL_PERIOD_NS[topic]
        jitter = {}
        for side in SIDES:
            received = arrivals.get(side_topic(side, topic), [])
            jitter[side] = summary_ms(jitter_ns(received, period_ns))
            lines.append(
                f'| {topic} | {period_ns / 1e6:.2f} | {SIDE_LABELS[side]} | '
                f'{len(received)} / {spec.counts[topic]} | {jitter[side]["median_ms"]:.3f} | '
                f'{jitter[side]["p95_ms"]:.3f} | {jitter[side]["max_ms"]:.3f} |'
            )
        lines.append(
            f'| {topic} | | ratio ours / reference | | '
            f'{_ratio(jitter["ours"]["median_ms"], jitter["reference"]["median_ms"])} | '
            f'{_ratio(jitter["ours"]["p95_ms"], jitter["reference"]["p95_ms"])} | '
            f'{_ratio(jitter["ours"]["max_ms"], jitter["reference"]["max_ms"])} |'
        )
    verdict = 'PASS' if passed else 'FAIL'
    lines += [
        '',
        f'Acceptance: median publish lateness of bag_player < {ACCEPT_MEDIAN_MS:g} ms at rate '
        f'1.0: **{verdict}** ({ours["median_ms"]:.3f} ms).',
        '',
    ]
    return '\n'.join(lines), passed


# -- command line -------------------------------------------------------------------------
def build_arg_parser() -> argparse.ArgumentParser:
    """Options of the benchmark (and the hidden ones of its subscriber process)."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--duration', type=float, default=20.0, help='bag length, s')
    parser.add_argument('--seed', type=int, default=0, help='seed of the image bytes')
    parser.add_argument('--output', type=Path, default=DEFAULT_OUTPUT, help='Markdown report')
    parser.add_argument(
        '--subscriber-qos',
        choices=('reliable', 'sensor'),
        default='reliable',
        help='subscriber QoS: reliable depth 10 (default) or the sensor-data profile',
    )
    parser.add_argument(
        '--workdir', type=Path, help='where to write the bag (default: a temp dir)'
    )
    parser.add_argument('--subscriber', type=Path, help=argparse.SUPPRESS)
    parser.add_argument('--subscribe', action='append', default=[], help=argparse.SUPPRESS)
    return parser


def run_benchmark(args: argparse.Namespace) -> int:
    """Write the bag, replay it both ways, print and save the report; 1 if it fails."""
    os.environ.setdefault('ROS_DOMAIN_ID', str(os.getpid() % 100 + 100))
    if 'FASTRTPS_DEFAULT_PROFILES_FILE' not in os.environ:
        print(
            'warning: scripts/env.sh is not sourced; DDS is not restricted to loopback',
            file=sys.stderr,
        )
    with tempfile.TemporaryDirectory(prefix='bench-lateness-', dir=args.workdir) as tmp:
        print(f'writing the bag ({args.duration:g} s) ...', file=sys.stderr)
        spec = write_bag(Path(tmp) / 'bag', duration_s=args.duration, seed=args.seed)
        topics = {
            side_topic(side, topic): msgtype
            for side in SIDES
            for topic, msgtype in ((IMAGE_TOPIC, IMAGE_TYPE), (ODOM_TOPIC, ODOM_TYPE))
        }
        rclpy.init()
        subscriber = SubscriberProcess(topics, Path(tmp) / 'arrivals.json', args.subscriber_qos)
        try:
            print('replaying with the naive loop (reference) ...', file=sys.stderr)
            phases = {'reference': run_reference(spec.path)}
            print('replaying with bag_player (ours) ...', file=sys.stderr)
            phases['ours'] = run_bag_player(spec.path)
            time.sleep(DRAIN_S)
            arrivals = subscriber.stop()
        finally:
            subscriber.close()
            rclpy.try_shutdown()
    report, passed = render_report(
        spec, phases, arrivals, seed=args.seed, subscriber_qos=args.subscriber_qos
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(report, encoding='utf-8')
    print(report)
    print(f'written to {args.output}', file=sys.stderr)
    return 0 if passed else 1


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, or the subscriber process when started with --subscriber."""
    parser = build_arg_parser()
    args = parser.parse_args(argv)
    if not args.duration > 0:
        parser.error(f'--duration must be > 0 s, got {args.duration}')
    if args.subscriber is not None:
        return run_subscriber(args.subscribe, args.subscriber, args.subscriber_qos)
    return run_benchmark(args)


if __name__ == '__main__':
    sys.exit(main())
