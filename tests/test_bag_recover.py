"""bag_recover: a recorder killed with SIGKILL, truncated bags, bad input.

The recorder test runs a real bag_recorder process on a topic the test publishes, kills it
with SIGKILL and checks that bag_recover gives back every message sent more than a second
before the kill. The truncation tests cut a valid bag at several points and check that
every chunk complete before the cut comes back, no more, no less.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
from bag_fixtures import read_back, tool_env
from rclpy.serialization import deserialize_message

from slam_core.errors import BagError
from slam_ros.bag.recover import recover
from slam_ros.testing.harness import RosHarness
from slam_ros.testing.messages import BagTopic, write_bag
from slam_ros.typesys import message_class

TOPICS = (
    BagTopic('/odom', 'nav_msgs/msg/Odometry', 100.0),
    BagTopic('/camera/camera_info', 'sensor_msgs/msg/CameraInfo', 30.0),
)


def run_recover(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ['bag_recover', *args], capture_output=True, text=True, timeout=60, env=tool_env()
    )


@pytest.mark.topic
def test_recorder_killed_with_sigkill_is_recovered(
    ros_harness: RosHarness, tmp_path: Path
) -> None:
    odometry = message_class('nav_msgs/msg/Odometry')
    publisher = ros_harness.publisher('/odom', odometry)
    recorder = ros_harness.start_process(
        'recorder', ['bag_recorder', '/odom', '-o', str(tmp_path / 'run')], env=tool_env()
    )
    ros_harness.wait_for_subscribers(publisher, timeout_s=30)
    sent: list[float] = []  # wall time each message was sent; its index is pose.x
    deadline = time.monotonic() + 4.0
    while time.monotonic() < deadline:
        message = odometry()
        message.pose.pose.position.x = float(len(sent))
        sent.append(time.monotonic())
        publisher.publish(message)
        time.sleep(0.01)
    killed_at = time.monotonic()
    os.kill(recorder.process.pid, signal.SIGKILL)
    assert recorder.process.wait(timeout=10) == -signal.SIGKILL
    assert not (tmp_path / 'run').exists()
    (staging,) = tmp_path.glob('.run.recording-*')

    refused = subprocess.run(
        ['bag_info', str(staging)], capture_output=True, text=True, timeout=60, env=tool_env()
    )
    assert refused.returncode == 2 and f'bag_recover {staging}' in refused.stderr
    before = sorted(p.stat().st_mtime_ns for p in staging.rglob('*'))
    result = run_recover(str(staging))
    assert result.returncode == 0, result.stderr
    assert sorted(p.stat().st_mtime_ns for p in staging.rglob('*')) == before  # input untouched
    assert '/odom: ' in result.stdout
    recovered = read_back(tmp_path / 'run')['/odom']
    indices = [int(deserialize_message(d, odometry).pose.pose.position.x) for d in recovered]
    old = sum(1 for t in sent if t < killed_at - 1.0)
    assert old > 100
    # A gap-free prefix of what was sent, holding everything older than 1 s before the kill.
    assert indices == list(range(len(indices)))
    assert len(indices) >= old, (len(indices), old, len(sent))


@pytest.fixture
def valid_bag(tmp_path: Path) -> Path:
    write_bag(tmp_path / 'valid', TOPICS, duration_s=30.0, seed=5)
    (path,) = (tmp_path / 'valid').glob('*.mcap')
    return path


def messages_in_chunks(path: Path) -> list[tuple[int, int]]:
    """(end offset of each chunk, messages in the chunks up to it), counted from a full read."""
    from rosbags.rosbag2.storage_mcap import McapReader

    reader = McapReader(path)
    reader.open()
    try:
        totals, total = [], 0
        for chunk in sorted(reader.chunks, key=lambda c: c.chunk_start_offset):
            total += sum(chunk.channel_count.values())
            totals.append((chunk.chunk_start_offset + chunk.chunk_length, total))
        return totals
    finally:
        reader.close()


def test_truncated_bag_keeps_every_complete_chunk(valid_bag: Path, tmp_path: Path) -> None:
    data = valid_bag.read_bytes()
    chunks = messages_in_chunks(valid_bag)
    assert len(chunks) >= 3, 'the bag must span several chunks'
    full = read_back(valid_bag.parent)
    cuts = [chunks[0][0] - 1, chunks[0][0], chunks[1][0] + 100, len(data) // 2, len(data) - 5]
    for number, cut in enumerate(cuts):
        damaged = tmp_path / f'cut{number}.mcap'
        damaged.write_bytes(data[:cut])
        out = tmp_path / f'out{number}'
        expected = sum(1 for end, _ in chunks if end <= cut)
        want = max((n for end, n in chunks if end <= cut), default=0)
        if not want:
            with pytest.raises(BagError, match='no complete message'):
                recover(damaged, out)
            assert not out.exists() and not list(tmp_path.glob(f'.out{number}*'))
            continue
        report = recover(damaged, out)
        assert report.chunks == expected, (cut, report)
        assert report.message_count == want, (cut, report)
        assert damaged.read_bytes() == data[:cut]
        got = read_back(out)
        for topic, messages in got.items():
            assert messages == full[topic][: len(messages)], (cut, topic)
        assert sum(len(m) for m in got.values()) == want


def test_truncated_bag_errors_suggest_bag_recover(valid_bag: Path, tmp_path: Path) -> None:
    damaged = tmp_path / 'cut.mcap'
    damaged.write_bytes(valid_bag.read_bytes()[: valid_bag.stat().st_size // 2])
    result = subprocess.run(
        ['bag_info', str(damaged)], capture_output=True, text=True, timeout=60, env=tool_env()
    )
    assert result.returncode == 2
    assert f'bag_recover {damaged}' in result.stderr


def test_complete_bag_is_copied_whole(valid_bag: Path, tmp_path: Path) -> None:
    result = run_recover(str(valid_bag.parent), '-o', str(tmp_path / 'copy'))
    assert result.returncode == 0, result.stderr
    assert 'dropped: nothing' in result.stdout
    assert read_back(tmp_path / 'copy') == read_back(valid_bag.parent)


@pytest.mark.parametrize(
    ('content', 'culprit'),
    [
        (b'', 'is empty'),
        (b'this is not a bag' * 50, 'mcap magic'),
        (b'\x89MCAP0\r\n', 'no complete'),
    ],
)
def test_bad_input_is_one_line_exit_2(tmp_path: Path, content: bytes, culprit: str) -> None:
    path = tmp_path / 'bad.mcap'
    path.write_bytes(content)
    result = run_recover(str(path))
    assert result.returncode == 2, result.stderr
    assert result.stderr.count('\n') == 1 and 'Traceback' not in result.stderr
    assert str(path) in result.stderr and culprit in result.stderr
    assert not (tmp_path / 'bad_recovered').exists()
    assert not list(tmp_path.glob('.bad_recovered*'))


def test_existing_output_and_missing_input_are_refused(valid_bag: Path, tmp_path: Path) -> None:
    (tmp_path / 'taken').mkdir()
    result = run_recover(str(valid_bag), '-o', str(tmp_path / 'taken'))
    assert result.returncode == 2 and 'exists already' in result.stderr
    assert not any((tmp_path / 'taken').iterdir())
    result = run_recover(str(tmp_path / 'nothing_here'))
    assert result.returncode == 2 and 'does not exist' in result.stderr
