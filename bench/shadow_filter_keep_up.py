"""Does shadow_filter keep up at 30 Hz? Its own inputs, recorded, played into it alone.

    python bench/shadow_filter_keep_up.py [--bag bags/dynamic_camera.mcap] [--runs 3]
                                          [--keep DIR]

1. ``slam_run monoslam_shadow.yaml --paced --bag BAG`` with a recorder of the shadow_filter's
   inputs (features, monoslam/pose, camera/camera_info, monoslam/revoked): paced, every
   image gets its features and its pose, whatever the machine's load.
2. The recording is rewritten with each message at its image stamp (the pose 15 ms after
   its features, as MonoSLAM's processing would put it), so that it plays at the camera's
   30 Hz, and played at rate 1 into a graph of shadow_filter alone (``--processes``: its own
   process, as in the live graph). Per run: the CPU time of the shadow_filter process from
   /proc over the playback (from its first frame to the player's last message), as a share
   of one core, and its final counts (frames processed, inputs dropped) from its log.

PASS when every run processed every frame of the recording with nothing dropped, at most
``CPU_LIMIT`` of a core (the median over the runs). The CPU share is the process's own
time, but on a machine shared with other work it still grows with the load (caches,
hyperthreads): the load average is printed with each run.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
CPU_LIMIT = 0.25
INPUTS = ('/features', '/monoslam/pose', '/camera/camera_info', '/monoslam/revoked')
OFFSET_NS = {'/features': 0, '/monoslam/pose': 15_000_000, '/camera/camera_info': -2_000_000}
REPLAY_GRAPH = """graph:
  description: shadow_filter alone on its recorded inputs
  exit_when_player_done: true
  use_sim_time: false
  nodes:
    - name: shadow_filter
      package: monoslam_shadow_node
      executable: shadow_filter
      plugin: monoslam_shadow_node.shadow_filter.node:ShadowFilterNode
      parameters: [package://monoslam_shadow_node/config/shadow_filter.yaml]
  player:
    rate: 1.0
    clock_hz: 0.0
    wait_for_subscribers_s: 5.0
"""
DONE = re.compile(r'\[shadow_filter\]: done: (\d+) frames.* (\d+) inputs dropped')


def record_inputs(bag: Path, directory: Path) -> Path:
    """Run the monocular graph paced on ``bag``, recording the shadow_filter's inputs."""
    import yaml

    from slam_bringup.graph_nodes import find_graph

    content = yaml.safe_load(find_graph('monoslam_shadow.yaml').read_text(encoding='utf-8'))
    content['graph']['recorder'] = {'topics': list(INPUTS), 'discovery_period_s': 0.2}
    graph = directory / 'record.yaml'
    graph.write_text(yaml.safe_dump(content, sort_keys=False), encoding='utf-8')
    recorded = directory / 'recorded'
    command = [sys.executable, '-m', 'slam_bringup.runner', str(graph), '--paced']
    command += ['--bag', str(bag.resolve()), '--record', str(recorded)]
    with (directory / 'record.log').open('w', encoding='utf-8') as log:
        subprocess.run(command, cwd=directory, check=True, stdout=log, stderr=subprocess.STDOUT)
    return recorded


def at_image_stamps(recorded: Path, out: Path) -> int:
    """Rewrite the recording with every message at its header stamp (plus ``OFFSET_NS``;
    a revocation 1 ms before the frame that follows it); return the number of frames."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    from slam_ros.typesys import TypeRegistry

    registry = TypeRegistry()
    messages = []
    with Reader(recorded) as reader:
        connections = {c.topic: c for c in reader.connections}
        for connection, _, data in reader.messages():
            registry.ensure(connection.msgtype)
            message: Any = registry.typestore.deserialize_cdr(data, connection.msgtype)
            stamp = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
            messages.append((connection.topic, stamp, data))
    frames = sorted(stamp for topic, stamp, _ in messages if topic == '/features')
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        added = {
            topic: registry.add_connection(
                writer,
                topic,
                connection.msgtype,
                getattr(connection.ext, 'offered_qos_profiles', []),
            )
            for topic, connection in connections.items()
        }
        timed = []
        for topic, stamp, data in messages:
            if topic == '/monoslam/revoked':  # stamped with its frame; before the next one
                later = [f for f in frames if f > stamp]
                timed.append((later[0] - 1_000_000 if later else stamp, topic, data))
            else:
                timed.append((stamp + OFFSET_NS[topic], topic, data))
        for timestamp, topic, data in sorted(timed, key=lambda item: item[0]):
            writer.write(added[topic], timestamp, data)
    return len(frames)


def cpu_seconds(pid: int) -> float:
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def node_pid(runner: int) -> int | None:
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit():
            continue
        try:
            command = (entry / 'cmdline').read_bytes()
            parent = int((entry / 'stat').read_text().rsplit(')', 1)[1].split()[1])
        except OSError:
            continue
        if parent == runner and b'__node:=shadow_filter' in command:
            return int(entry.name)
    return None


def replay(inputs: Path, directory: Path) -> tuple[float, int, int, float]:
    """Play ``inputs`` at rate 1 into shadow_filter; return its CPU share of one core over
    the playback, frames processed, inputs dropped and the load average at the end."""
    graph = directory / 'replay.yaml'
    graph.write_text(REPLAY_GRAPH, encoding='utf-8')
    log = directory / 'replay.log'
    command = [sys.executable, '-m', 'slam_bringup.runner', str(graph), '--processes']
    with log.open('w', encoding='utf-8') as output:
        runner = subprocess.Popen(
            [*command, '--bag', str(inputs)], cwd=directory, stdout=output,
            stderr=subprocess.STDOUT,
        )  # fmt: skip
        pid = None
        while pid is None and runner.poll() is None:
            time.sleep(0.1)
            pid = node_pid(runner.pid)
        while runner.poll() is None and 'shadow_filter]: camera:' not in log.read_text():
            time.sleep(0.02)
        if pid is None:
            raise SystemExit(f'shadow_filter did not start; see {log}')
        start, started = cpu_seconds(pid), time.monotonic()
        end, ended = start, started
        while runner.poll() is None and 'bag_player]: published' not in log.read_text():
            try:
                end, ended = cpu_seconds(pid), time.monotonic()
            except OSError:
                break
            time.sleep(0.1)
        runner.wait(timeout=300)
    found = DONE.search(log.read_text())
    if found is None:
        raise SystemExit(f'shadow_filter wrote no final counts; see {log}')
    share = (end - start) / max(ended - started, 1e-9)
    return share, int(found.group(1)), int(found.group(2)), os.getloadavg()[0]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--bag', type=Path, default=ROOT / 'bags' / 'dynamic_camera.mcap')
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument('--keep', type=Path, help='keep the recordings and logs here')
    args = parser.parse_args()
    os.environ.setdefault('ROS_DOMAIN_ID', str(os.getpid() % 100 + 100))
    with tempfile.TemporaryDirectory(prefix='shadow_keep_up-') as scratch:
        directory = args.keep or Path(scratch)
        directory.mkdir(parents=True, exist_ok=True)
        recorded = record_inputs(args.bag, directory)
        inputs = directory / 'inputs.mcap'
        inputs.unlink(missing_ok=True)
        frames = at_image_stamps(recorded, inputs)
        print(f'{frames} frames of shadow_filter inputs recorded from {args.bag.name} (paced)')
        shares, every = [], True
        for run in range(args.runs):
            share, processed, dropped, load = replay(inputs, directory)
            shares.append(share)
            every &= processed == frames and dropped == 0
            print(
                f'run {run + 1}: CPU {100 * share:.1f} % of a core, {processed} of {frames} '
                f'frames processed, {dropped} inputs dropped (load average {load:.1f})'
            )
        median = sorted(shares)[len(shares) // 2]
        ok = every and median <= CPU_LIMIT
        print(
            f'{"PASS" if ok else "FAIL"}: median CPU {100 * median:.1f} % of a core (limit '
            f'{100 * CPU_LIMIT:.0f} %); every frame processed, none dropped: '
            f'{"yes" if every else "no"}'
        )
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
