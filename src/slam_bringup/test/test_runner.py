"""slam_run end to end: play a bag written in tmp_path, record it, compare every message."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from dataclasses import fields, is_dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from slam_bringup import runner
from slam_bringup.graph import load_graph
from slam_bringup.graph_nodes import node_descriptions
from slam_core.errors import GraphError
from slam_ros.bag.source import BagSource
from slam_ros.qos import output_qos
from slam_ros.testing.harness import RosHarness

# An isolated DDS domain for these tests, unless a harness chose one already.
os.environ.setdefault('ROS_DOMAIN_ID', str(os.getpid() % 100 + 100))

pytestmark = pytest.mark.topic

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
ODOMETRY = 'nav_msgs/msg/Odometry'
STRING = 'std_msgs/msg/String'
START_NS = 1_700_000_000_000_000_000
RUN_TIMEOUT_S = 120.0
TYPES = {'/odom': ODOMETRY, '/chatter': STRING}


def odometry(index: int) -> object:
    """A distinct Odometry message: the robot drives along x, covariances vary."""
    types = TYPESTORE.types
    stamp_ns = START_NS + index * 20_000_000
    header = types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](
            sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9
        ),
        frame_id='odom',
    )
    pose = types['geometry_msgs/msg/Pose'](
        position=types['geometry_msgs/msg/Point'](x=0.1 * index, y=0.0, z=0.0),
        orientation=types['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    twist = types['geometry_msgs/msg/Twist'](
        linear=types['geometry_msgs/msg/Vector3'](x=0.5, y=0.0, z=0.0),
        angular=types['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.01 * index),
    )
    covariance = np.arange(36, dtype=np.float64) * (index + 1)
    return types[ODOMETRY](
        header=header,
        child_frame_id='base_link',
        pose=types['geometry_msgs/msg/PoseWithCovariance'](pose=pose, covariance=covariance),
        twist=types['geometry_msgs/msg/TwistWithCovariance'](twist=twist, covariance=covariance),
    )


def write_bag(path: Path, odometry_count: int = 30) -> dict[str, list[object]]:
    """Write /odom (Odometry, 50 Hz) and /chatter (String, 10 Hz); return content per topic."""
    sent: dict[str, list[bytes]] = {'/odom': [], '/chatter': []}
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        odom = writer.add_connection('/odom', ODOMETRY, typestore=TYPESTORE)
        chatter = writer.add_connection('/chatter', STRING, typestore=TYPESTORE)
        for index in range(odometry_count):
            stamp_ns = START_NS + index * 20_000_000
            data = bytes(TYPESTORE.serialize_cdr(odometry(index), ODOMETRY))
            writer.write(odom, stamp_ns, data)
            sent['/odom'].append(data)
            if index % 5 == 0:
                text = TYPESTORE.types[STRING](data=f'message {index // 5}')
                data = bytes(TYPESTORE.serialize_cdr(text, STRING))
                writer.write(chatter, stamp_ns + 1, data)
                sent['/chatter'].append(data)
    return {topic: [content(TYPES[topic], data) for data in cdr] for topic, cdr in sent.items()}


def content(msgtype: str, data: bytes) -> object:
    """Decode CDR into plain lists and dicts (DDS may pad the CDR across processes)."""
    return plain(TYPESTORE.deserialize_cdr(data, msgtype))


def plain(value: object) -> object:
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: plain(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, list):
        return [plain(item) for item in value]
    return value


def read_back(path: Path) -> dict[str, list[object]]:
    """Return the content of every message per topic, in order."""
    received: dict[str, list[object]] = {}
    with BagSource(path) as source:
        for message in source.messages():
            decoded = content(message.msgtype, message.data)
            received.setdefault(message.topic, []).append(decoded)
    return received


def write_graph(
    directory: Path,
    *,
    exit_when_player_done: bool = True,
    use_sim_time: bool = False,
    player: dict[str, object] | None = None,
    nodes: list[dict[str, object]] | None = None,
    topics: tuple[str, ...] = ('/odom', '/chatter'),
) -> Path:
    """A GRAPH that plays ``directory/input`` and records ``topics`` (empty: all)."""
    graph = {
        'description': 'test replay',
        'use_sim_time': use_sim_time,
        'exit_when_player_done': exit_when_player_done,
        'nodes': nodes or [],
        'player': {'bag': 'input', 'wait_for_subscribers_s': 20.0, **(player or {})},
        'recorder': {'topics': list(topics), 'discovery_period_s': 0.1},
    }
    path = directory / 'graph.yaml'
    path.write_text(yaml.safe_dump({'graph': graph}))
    return path


def slam_run(*arguments: str) -> list[str]:
    return [sys.executable, '-m', 'slam_bringup.runner', *arguments]


def tool_env() -> dict[str, str]:
    return {**os.environ, 'PYTHONUNBUFFERED': '1', 'RCUTILS_COLORIZED_OUTPUT': '0'}


def run_graph(*arguments: str) -> subprocess.CompletedProcess[str]:
    """Run slam_run to its end; its output is captured."""
    return subprocess.run(
        slam_run(*arguments),
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT_S,
        env=tool_env(),
        check=False,
    )


class LineWatcher:
    """Collects a process's stderr lines in a thread; waits for a line with a deadline."""

    def __init__(self, process: subprocess.Popen[str]) -> None:
        assert process.stderr is not None
        self.lines: list[str] = []
        self._queue: queue.Queue[str] = queue.Queue()
        self._thread = threading.Thread(target=self._read, args=(process.stderr,), daemon=True)
        self._thread.start()

    def _read(self, stream: object) -> None:
        for line in stream:  # type: ignore[attr-defined]
            self._queue.put(line)

    def wait_for(self, text: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self._queue.get(timeout=max(deadline - time.monotonic(), 0.0))
            except queue.Empty:
                break
            self.lines.append(line)
            if text in line:
                return
        pytest.fail(f'no line with {text!r} within {timeout_s} s; stderr:\n{"".join(self.lines)}')

    def rest(self) -> str:
        self._thread.join(timeout=10.0)
        while not self._queue.empty():
            self.lines.append(self._queue.get())
        return ''.join(self.lines)


def one_error_line(stderr: str) -> str:
    assert 'Traceback' not in stderr, stderr
    errors = [line for line in stderr.splitlines() if ': error: ' in line]
    assert len(errors) == 1, stderr
    return errors[0]


# -- end to end ---------------------------------------------------------------------------
def test_in_process_run_records_every_message(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sent = write_bag(tmp_path / 'input')
    graph = write_graph(tmp_path, use_sim_time=True)
    status = runner.main([str(graph), '--record', str(tmp_path / 'output')])
    assert status == 0
    assert read_back(tmp_path / 'output') == sent
    summary = capsys.readouterr().out
    assert 'published 36 messages' in summary
    assert 'wrote 36 messages' in summary


def test_processes_run_records_every_message(tmp_path: Path) -> None:
    # Not use_sim_time: bag_recorder's discovery timer runs on the node clock, which stands
    # still until the player's first /clock, and the player waits for the recorder.
    sent = write_bag(tmp_path / 'input')
    graph = write_graph(tmp_path)
    result = run_graph(str(graph), '--processes', '--record', str(tmp_path / 'output'))
    assert result.returncode == 0, result.stderr
    assert read_back(tmp_path / 'output') == sent
    assert 'bag_player: exit code 0' in result.stdout
    assert 'bag_recorder: exit code 0' in result.stdout


def test_processes_run_drains_while_recording_every_topic_and_reports(
    ros_harness: RosHarness, tmp_path: Path
) -> None:
    """With every topic recorded, the recorder takes /diagnostics every second, its own
    reports included: the drain does not wait for it. The reports of the player and the
    recorder count what they published, received and wrote; the player starts when /odom has
    a subscriber, which may be the recorder before odometry_ingest: the ingest's count is
    from the first message it took."""
    diagnostics = ros_harness.collect('/diagnostics', DiagnosticArray, output_qos(depth=1000))
    write_bag(tmp_path / 'input', odometry_count=300)
    ingest = {
        'name': 'odometry_ingest',
        'package': 'em_sam_node',
        'executable': 'odometry_ingest',
        'parameters': ['package://em_sam_node/config/odometry_ingest.yaml'],
    }
    graph = write_graph(tmp_path, nodes=[ingest], topics=())
    result = run_graph(str(graph), '--processes', '--record', str(tmp_path / 'output'))
    assert result.returncode == 0, result.stderr
    assert 'still busy' not in result.stderr, result.stderr
    last: dict[str, dict[str, str]] = {}
    for array in list(diagnostics.messages):
        for status in array.status:
            last[status.name] = {value.key: value.value for value in status.values}
    assert {'/odometry_ingest', '/bag_player', '/bag_recorder'} <= set(last), result.stderr
    player = last['/bag_player']
    published = (player['published /odom'], player['published /chatter'], player['skipped'])
    assert published == ('300', '60', '0'), player
    for name, input in (('/odometry_ingest', 'odom'), ('/bag_recorder', '/odom')):
        report = last[name]
        taken = int(report[f'received {input}']) + int(report[f'lost {input}'])
        assert taken == 300 - int(report[f'first sequence {input}']) + 1, report
    recorder = last['/bag_recorder']  # its report once the bag was finalized
    for topic in ('/odom', '/chatter'):
        assert recorder[f'written {topic}'] == recorder[f'received {topic}'], recorder
    names = set()
    with BagSource(tmp_path / 'output') as source:
        assert {'/odom', '/chatter', '/odometry_increments'} <= set(source.topics())
        for message in source.messages():
            if message.topic == '/diagnostics':
                array = TYPESTORE.deserialize_cdr(message.data, message.msgtype)
                names |= {status.name for status in array.status}
    assert {'/bag_recorder', '/odometry_ingest'} <= names  # it recorded its own reports


@pytest.mark.parametrize(
    ('mode', 'stop_signal', 'marker'),
    [
        ((), signal.SIGINT, 'the player has finished'),
        (('--processes',), signal.SIGTERM, "node 'bag_player' exited"),
    ],
    ids=['in-process-sigint', 'processes-sigterm'],
)
def test_signal_stops_graph_and_finalizes_recording(
    tmp_path: Path, mode: tuple[str, ...], stop_signal: signal.Signals, marker: str
) -> None:
    sent = write_bag(tmp_path / 'input')
    graph = write_graph(tmp_path, exit_when_player_done=False)
    command = slam_run(str(graph), *mode, '--record', str(tmp_path / 'output'))
    with subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=tool_env()
    ) as process:
        watcher = LineWatcher(process)
        try:
            watcher.wait_for(marker, RUN_TIMEOUT_S)
            process.send_signal(stop_signal)
            status = process.wait(timeout=RUN_TIMEOUT_S)
        finally:
            if process.poll() is None:
                process.kill()
        stderr = watcher.rest()
    assert status == 0, stderr
    assert 'Traceback' not in stderr
    assert read_back(tmp_path / 'output') == sent


# -- failures -----------------------------------------------------------------------------
def test_invalid_graph_gives_one_line_and_exit_2(tmp_path: Path) -> None:
    path = tmp_path / 'graph.yaml'
    path.write_text(yaml.safe_dump({'graph': {'nodes': [{'name': 'a', 'packge': 'p'}]}}))
    result = subprocess.run(
        slam_run(str(path)), capture_output=True, text=True, timeout=RUN_TIMEOUT_S, check=False
    )
    assert result.returncode == 2
    assert 'Traceback' not in result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert str(path) in line
    assert 'graph.nodes[0].packge' in line


def test_node_rejecting_parameters_names_node_and_exits_2(tmp_path: Path) -> None:
    write_bag(tmp_path / 'input')
    graph = write_graph(tmp_path, player={'topics': ['/no_such_topic']})
    result = run_graph(str(graph), '--record', str(tmp_path / 'output'))
    assert result.returncode == 2
    line = one_error_line(result.stderr)
    assert "graph.player: node 'bag_player'" in line
    assert '/no_such_topic' in line
    assert not (tmp_path / 'output').exists()  # the recorder starts after the player


def test_player_error_during_playback_exits_nonzero(tmp_path: Path) -> None:
    write_bag(tmp_path / 'input', odometry_count=400)
    (mcap,) = (tmp_path / 'input').glob('*.mcap')
    data = bytearray(mcap.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 4096] = b'\xff' * 4096  # lengths of strings and records blow up
    mcap.write_bytes(bytes(data))
    graph = write_graph(tmp_path, player={'rate': 50.0})
    result = run_graph(str(graph), '--record', str(tmp_path / 'output'))
    assert result.returncode == 2
    assert 'corrupt' in one_error_line(result.stderr)
    assert (tmp_path / 'output').is_dir()  # what was received is still finalized


def test_failing_node_process_stops_graph(tmp_path: Path) -> None:
    write_bag(tmp_path / 'input')
    broken: dict[str, object] = {'name': 'broken', 'package': 'coreutils', 'executable': 'false'}
    graph = write_graph(tmp_path, player={'loop': True}, nodes=[broken])
    result = run_graph(str(graph), '--processes', '--record', str(tmp_path / 'output'))
    assert result.returncode == 1
    # Not one_error_line: the other children may still be importing Python when they get
    # SIGINT, and then print a KeyboardInterrupt traceback of their own.
    (line,) = [x for x in result.stderr.splitlines() if x.startswith('slam_run: error:')]
    assert "graph.nodes[0]: node 'broken' exited with code 1" in line


class FailingNode(Node):
    """A node whose timer callback raises, as a node with a bug would."""

    def __init__(self, **kwargs: object) -> None:
        super().__init__('failing', **kwargs)  # type: ignore[arg-type]
        self.create_timer(0.01, self._fail)

    def _fail(self) -> None:
        raise RuntimeError('bug in a callback')


class QuietNode(Node):
    """A node with a timer that works."""

    def __init__(self, **kwargs: object) -> None:
        super().__init__('quiet', **kwargs)  # type: ignore[arg-type]
        self.create_timer(0.01, lambda: None)


def test_exception_in_callback_stops_graph_with_exit_1_naming_the_node(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    nodes = [
        {'name': 'q', 'package': 'p', 'executable': 'e', 'plugin': f'{__name__}:QuietNode'},
        {'name': 'f', 'package': 'p', 'executable': 'e', 'plugin': f'{__name__}:FailingNode'},
    ]
    path = tmp_path / 'graph.yaml'
    path.write_text(yaml.safe_dump({'graph': {'nodes': nodes}}))
    assert runner.main([str(path)]) == 1
    err = capsys.readouterr().err
    assert 'RuntimeError: bug in a callback' in err
    assert 'slam_run: error: /f: a callback raised RuntimeError: bug in a callback' in err


@pytest.mark.parametrize(
    ('plugin', 'reason'),
    [(None, 'not set'), ('no_such_package.module:Node', "cannot import 'no_such_package")],
)
def test_in_process_needs_an_importable_plugin(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], plugin: str | None, reason: str
) -> None:
    node = {'name': 'a', 'package': 'p', 'executable': 'e'}
    if plugin is not None:
        node['plugin'] = plugin
    path = tmp_path / 'graph.yaml'
    path.write_text(yaml.safe_dump({'graph': {'nodes': [node]}}))
    assert runner.main([str(path)]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert 'graph.nodes[0].plugin' in line
    assert reason in line


def test_missing_executable_is_named(tmp_path: Path) -> None:
    path = tmp_path / 'graph.yaml'
    node = {'name': 'a', 'package': 'no_such_package', 'executable': 'no_such_executable'}
    path.write_text(yaml.safe_dump({'graph': {'nodes': [node]}}))
    graph = load_graph(path)
    with pytest.raises(GraphError, match=r"graph\.nodes\[0\]\.executable: 'no_such_executable'"):
        runner.executable(graph, node_descriptions(graph)[0])


def test_nodes_finishing_after_sigint_are_waited_for_and_named(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A node still writing its report after SIGINT is given time (up to the timeout) and
    named while the runner waits; the wait ends as soon as it exits."""
    monkeypatch.setattr(runner, 'WAIT_LOG_PERIOD_S', 0.2)
    slow = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(1.0)'])
    child = SimpleNamespace(description=SimpleNamespace(name='em_sam_mapper'), process=slow)
    started = time.monotonic()
    runner.wait_for([child], timeout_s=30.0)  # type: ignore[list-item]
    assert slow.poll() == 0 and time.monotonic() - started < 10.0
    assert 'waiting for em_sam_mapper to finish' in capsys.readouterr().err
    hung = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])
    child.process = hung
    started = time.monotonic()
    runner.wait_for([child], timeout_s=0.5)  # type: ignore[list-item]
    assert hung.poll() is None and time.monotonic() - started < 5.0  # the timeout holds
    hung.kill()
    hung.wait()
