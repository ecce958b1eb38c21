"""Fault table, recording rows: a recorder killed with SIGKILL, a bag cut short.

(a) ``--runs`` times: bag_recorder records every topic of ``bags/office_camera.mcap`` while
    bag_player replays it at rate 1; at a random moment 2-58 s into the replay the recorder
    is killed with SIGKILL, then ``bag_recover`` rebuilds the bag from its staging
    directory. A probe node in this process subscribes to the same topics (once the
    recorder has, so the player waits for the recorder) and notes when each message
    arrived. PASS when every message the probe got more than 1 s before the kill is in the
    recovered bag (matched by topic and CDR bytes, header stamp included) and the bag holds
    nothing that is not in the source bag. The run uses its own ROS_DOMAIN_ID.
(b) ``--cuts`` times: the source bag is cut at a random byte; PASS when ``bag_recover``
    gives exactly the messages of the chunks that end before the cut (exit 2 and nothing
    written when no chunk does).

Prints a markdown table with PASS/FAIL per row and a summary; exits 1 on a FAIL.

Run (after ``bash scripts/bootstrap.sh``)::

    source scripts/env.sh
    python bench/fault_recording.py [--runs 20] [--cuts 10] [--seed N]
"""

from __future__ import annotations

import argparse
import functools
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import rclpy
from bench_common import source_revision
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbags.rosbag2.storage_mcap import McapReader

from slam_ros.bag.source import BagSource
from slam_ros.typesys import message_class

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / 'bags' / 'office_camera.mcap'
MARGIN_S = 1.0
NOT_RECORDED = ('/clock', '/diagnostics', '/rosout', '/parameter_events')


def padded(data: bytes) -> bytes:
    """CDR as it comes off DDS: padded with zeros to a multiple of 4 bytes."""
    return data + b'\0' * (-len(data) % 4)


def read(path: Path) -> list[tuple[str, int, bytes]]:
    """(topic, stamp ns, CDR) of every message of a bag."""
    with BagSource(path) as source:
        return [(m.topic, m.timestamp_ns, padded(m.data)) for m in source.messages()]


def recover(source: Path, output: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ['bag_recover', str(source), '-o', str(output)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def wait_for_line(log: Path, text: str, count: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if log.exists() and log.read_text(errors='replace').count(text) >= count:
            return True
        time.sleep(0.1)
    return False


class Probe:
    """Subscribes to the bag's topics (raw CDR) and notes when each message arrived."""

    def __init__(self, topics: dict[str, str]) -> None:
        self.node = rclpy.create_node('fault_probe')
        self.arrivals: list[tuple[str, bytes, int]] = []
        self.topics = topics
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.running = True
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def subscribe(self) -> None:
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        for topic, msgtype in self.topics.items():
            self.node.create_subscription(
                message_class(msgtype),
                topic,
                functools.partial(self._arrived, topic),
                qos,
                raw=True,
            )

    def _arrived(self, topic: str, data: bytes) -> None:
        self.arrivals.append((topic, padded(data), time.time_ns()))

    def _spin(self) -> None:
        while self.running:
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self.running = False
        self.thread.join()
        self.executor.remove_node(self.node)
        self.node.destroy_node()


def kill_run(
    number: int, rng: random.Random, source: list[tuple[str, int, bytes]], work: Path
) -> list[str]:
    """One SIGKILL row: returns the table cells."""
    with BagSource(BAG) as bag:
        topics = {name: info.msgtype for name, info in bag.topics().items()}
    run = work / f'run{number}'
    run.mkdir()
    env = {**os.environ, 'PYTHONUNBUFFERED': '1', 'RCUTILS_COLORIZED_OUTPUT': '0'}
    rec_log, play_log = run / 'recorder.log', run / 'player.log'
    probe = Probe(topics)
    with rec_log.open('wb') as out:
        recorder = subprocess.Popen(
            ['bag_recorder', '-a', '--exclude', *NOT_RECORDED, '-o', str(run / 'bag')],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
        )
    with play_log.open('wb') as out:
        player = subprocess.Popen(
            ['bag_player', str(BAG), '--wait-for-subscribers', '30'],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
        )
    try:
        # The probe subscribes once the recorder has: the player must wait for the recorder.
        if not wait_for_line(rec_log, "recording '/", len(topics), 60):
            return [str(number), '-', '-', '-', '-', 'FAIL (recorder never subscribed)']
        started = time.monotonic()
        probe.subscribe()
        time.sleep(rng.uniform(2.0, 58.0))
        killed_at_ns = time.time_ns()
        os.kill(recorder.pid, signal.SIGKILL)
        recorder.wait(timeout=10)
        kill_s = time.monotonic() - started
    finally:
        probe.close()
        player.send_signal(signal.SIGINT)
        try:
            player.wait(timeout=20)
        except subprocess.TimeoutExpired:
            player.kill()
            player.wait()
        if recorder.poll() is None:
            recorder.kill()
            recorder.wait()
    (staging,) = run.glob('.bag.recording-*')
    result = recover(staging, run / 'bag')
    if result.returncode != 0:
        return [str(number), f'{kill_s:.1f}', '0', '-', '-', f'FAIL ({result.stderr.strip()})']
    recovered = Counter((topic, data) for topic, _, data in read(run / 'bag'))
    known = {(topic, data) for topic, _, data in source}
    foreign = sum(n for key, n in recovered.items() if key not in known)
    cutoff = killed_at_ns - int(MARGIN_S * 1e9)
    expected = Counter((topic, data) for topic, data, at in probe.arrivals if at < cutoff)
    missing = sum((expected - recovered).values())
    return [
        str(number),
        f'{kill_s:.1f}',
        str(sum(recovered.values())),
        str(sum(expected.values())),
        f'{missing} / {foreign}',
        'PASS' if missing == 0 and foreign == 0 else 'FAIL',
    ]


def cut_row(
    number: int,
    rng: random.Random,
    data: bytes,
    chunks: list[tuple[int, int, list[tuple[str, int, bytes]]]],
    work: Path,
) -> list[str]:
    """One truncation row: returns the table cells."""
    cut = rng.randrange(9, len(data))
    damaged = work / f'cut{number}.mcap'
    damaged.write_bytes(data[:cut])
    complete = [c for c in chunks if c[0] <= cut]
    expected = sum(c[1] for c in complete)
    result = recover(damaged, work / f'cut{number}')
    if not expected:
        ok = result.returncode == 2 and not (work / f'cut{number}').exists()
        got = 0
    else:
        got_messages = read(work / f'cut{number}') if result.returncode == 0 else []
        got = len(got_messages)
        ok = result.returncode == 0 and Counter(got_messages) == Counter(
            m for c in complete for m in c[2]
        )
    damaged.unlink()
    return [
        str(number),
        f'{cut} of {len(data)}',
        f'{len(complete)} / {expected}',
        str(got),
        'PASS' if ok else 'FAIL',
    ]


def source_chunks() -> list[tuple[int, int, list[tuple[str, int, bytes]]]]:
    """(end offset, message count, messages) of each chunk of the source bag, by offset,
    read through rosbags' own index one chunk at a time."""
    reader = McapReader(BAG)
    reader.open()
    try:
        infos = sorted(reader.chunks, key=lambda c: c.chunk_start_offset)
        out = []
        for info in infos:
            reader.chunks = [info]
            messages = [
                (c.topic, stamp, padded(bytes(data)))
                for c, stamp, data in reader.messages(reader.connections)
            ]
            out.append((info.chunk_start_offset + info.chunk_length, len(messages), messages))
        return out
    finally:
        reader.close()


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(row) + ' |' for row in rows]
    return '\n'.join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', type=int, default=20, help='SIGKILL runs (row a)')
    parser.add_argument('--cuts', type=int, default=10, help='truncation points (row b)')
    parser.add_argument('--seed', type=int, default=None, help='random seed (default: random)')
    args = parser.parse_args()
    if not BAG.exists():
        print(f'fault_recording: error: {BAG} is missing', file=sys.stderr)
        return 2
    seed = args.seed if args.seed is not None else random.SystemRandom().randrange(10**6)
    rng = random.Random(seed)
    os.environ.setdefault('ROS_DOMAIN_ID', str(os.getpid() % 100 + 100))
    rclpy.init()
    print(f'seed {seed}, source {source_revision()}, bag {BAG.name}', flush=True)
    try:
        return run(args.runs, args.cuts, rng, seed)
    finally:
        rclpy.try_shutdown()


def run(runs: int, cut_count: int, rng: random.Random, seed: int) -> int:
    """Run the rows, print the tables; 1 on a FAIL."""
    source = read(BAG)
    kills: list[list[str]] = []
    cuts: list[list[str]] = []
    with tempfile.TemporaryDirectory(prefix='fault_recording_') as tmp:
        work = Path(tmp)
        for number in range(1, runs + 1):
            kills.append(kill_run(number, rng, source, work))
            print(' '.join(kills[-1]), flush=True)
        data = BAG.read_bytes()
        chunks = source_chunks()
        for number in range(1, cut_count + 1):
            cuts.append(cut_row(number, rng, data, chunks, work))
            print(' '.join(cuts[-1]), flush=True)
    print()
    print(
        '(a) SIGKILL of bag_recorder during a replay of office_camera.mcap, then bag_recover '
        f'(seed {seed}):\n'
    )
    header = ['run', 'kill at (s)', 'recovered', 'received > 1 s before kill']
    print(table([*header, 'missing / foreign', 'result'], kills))
    print(f'\n(b) office_camera.mcap cut at {cut_count} random bytes, then bag_recover:\n')
    print(
        table(['cut', 'at byte', 'complete chunks / their messages', 'recovered', 'result'], cuts)
    )
    failed = [r for r in kills + cuts if not r[-1].startswith('PASS')]
    print(
        f'\nSummary: (a) {sum(r[-1] == "PASS" for r in kills)}/{len(kills)} PASS, '
        f'(b) {sum(r[-1] == "PASS" for r in cuts)}/{len(cuts)} PASS: '
        + ('FAIL' if failed else 'PASS')
    )
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
