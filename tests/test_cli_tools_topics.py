"""slam_echo, slam_diag and slam_call against real nodes over DDS, run as a user runs them.

Each tool runs as an installed console script in this test's ROS domain; the graph side is
the harness's probe node (publishers, a Trigger server) or a real ``em_sam_mapper``.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path as PathMsg
from std_msgs.msg import String
from std_srvs.srv import Trigger

from slam_ros.qos import latched_qos, output_qos
from slam_ros.testing.harness import RosHarness

pytestmark = pytest.mark.topic
TOOL_TIMEOUT_S = 60.0


def run_tool(*command: str) -> subprocess.CompletedProcess[str]:
    """Run a command-line tool to its end; its output as text."""
    return subprocess.run(
        list(command), capture_output=True, text=True, timeout=TOOL_TIMEOUT_S, check=False
    )


def latched_path(harness: RosHarness, count: int) -> PathMsg:
    """Publish a latched nav_msgs/Path of ``count`` poses on /cli_test/path; return it."""
    message = PathMsg()
    message.header.frame_id = 'map'
    message.header.stamp.sec = 17
    for index in range(count):
        pose = PoseStamped()
        pose.header.frame_id = 'map'
        pose.pose.position.x = 0.5 * index
        pose.pose.orientation.w = 1.0
        message.poses.append(pose)
    harness.publisher('/cli_test/path', PathMsg, latched_qos(depth=1)).publish(message)
    return message


def test_echo_once_prints_a_latched_message_as_yaml(ros_harness: RosHarness) -> None:
    latched_path(ros_harness, 3)
    result = run_tool('slam_echo', 'cli_test/path', '--once')
    assert result.returncode == 0, result.stderr
    document = next(d for d in yaml.safe_load_all(result.stdout) if d is not None)
    assert document['header'] == {'stamp': {'sec': 17, 'nanosec': 0}, 'frame_id': 'map'}
    assert [p['pose']['position']['x'] for p in document['poses']] == [0.0, 0.5, 1.0]
    assert document['poses'][2]['pose']['orientation']['w'] == 1.0
    assert '/cli_test/path: 1 received, 1 printed' in result.stderr


def test_echo_field_and_no_arr(ros_harness: RosHarness) -> None:
    latched_path(ros_harness, 200)
    field = run_tool('slam_echo', '/cli_test/path', '--once', '--field', 'poses.199.pose.position')
    assert field.returncode == 0, field.stderr
    assert yaml.safe_load(field.stdout.split('---')[0]) == {'x': 99.5, 'y': 0.0, 'z': 0.0}
    no_arr = run_tool('slam_echo', '/cli_test/path', '--once', '--no-arr')
    assert yaml.safe_load(no_arr.stdout.split('---')[0])['poses'] == '<sequence of 200>'
    cut = run_tool('slam_echo', '/cli_test/path', '--once')
    poses = yaml.safe_load(cut.stdout.split('---')[0])['poses']
    assert len(poses) == 129 and poses[-1] == '...'
    wrong = run_tool('slam_echo', '/cli_test/path', '--once', '--field', 'header.stump')
    assert wrong.returncode == 2 and "no 'stump' here (it has: stamp, frame_id)" in wrong.stderr


def test_echo_names_a_topic_that_is_not_there(ros_harness: RosHarness) -> None:
    latched_path(ros_harness, 1)
    # the tool's fresh DDS participant must discover the publisher before the wait ends: 2 s
    # was not enough on a busy 2-core machine (it saw only /parameter_events)
    result = run_tool('slam_echo', '/cli_test/pth', '--once', '--wait', '6')
    assert result.returncode == 2
    assert "no topic '/cli_test/pth' on the ROS graph" in result.stderr
    assert "did you mean '/cli_test/path'" in result.stderr


def test_echo_times_out_on_a_silent_topic(ros_harness: RosHarness) -> None:
    ros_harness.publisher('/cli_test/silent', String, output_qos())
    result = run_tool('slam_echo', '/cli_test/silent', '--once', '--timeout', '2')
    assert result.returncode == 1, result.stderr
    assert 'no message on /cli_test/silent within 2 s (1 publisher(s)' in result.stderr
    assert '0 received, 0 printed' in result.stderr


def diagnostics(levels: dict[str, bytes]) -> DiagnosticArray:
    """A DiagnosticArray with one status per name at ``levels``."""
    array = DiagnosticArray()
    for name, level in levels.items():
        status = DiagnosticStatus(name=name, level=level, message=f'{name} says hello')
        status.values.append(KeyValue(key='received odom', value='42'))
        array.status.append(status)
    return array


def test_diag_once_shows_the_table_worst_first(ros_harness: RosHarness) -> None:
    publisher = ros_harness.publisher('/diagnostics', DiagnosticArray, output_qos())
    array = diagnostics({'/fine_node': DiagnosticStatus.OK, '/slow_node': DiagnosticStatus.WARN})
    timer = ros_harness.node.create_timer(0.2, lambda: publisher.publish(array))
    try:
        result = run_tool('slam_diag', '--once', '--wait', '8', '-v')  # discovery, when busy
    finally:
        ros_harness.node.destroy_timer(timer)
    assert result.returncode == 1, result.stdout + result.stderr  # the worst is WARN
    lines = result.stdout.splitlines()
    assert lines[0].split() == ['LEVEL', 'NAME', 'AGE', 'MESSAGE']
    assert lines[1].startswith('WARN') and '/slow_node' in lines[1]
    assert 'slow_node says hello' in lines[1]
    assert 'received odom: 42' in lines[2]
    assert any(line.startswith('OK') and '/fine_node' in line for line in lines)
    assert lines[-1] == '2 statuses: 1 WARN, 1 OK'


def test_diag_once_says_when_nothing_came(ros_harness: RosHarness) -> None:
    result = run_tool('slam_diag', '--once', '--wait', '1', '--topic', '/cli_test/no_diag')
    assert result.returncode == 4
    assert 'no diagnostics yet (0 messages on /diagnostics)' in result.stdout


def test_call_trigger_and_exit_status(ros_harness: RosHarness) -> None:
    calls: list[int] = []

    def on_call(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        calls.append(1)
        response.success = len(calls) == 1
        response.message = f'call {len(calls)}'
        return response

    ros_harness.node.create_service(Trigger, '/cli_test_server/do_it', on_call)
    first = run_tool('slam_call', 'do_it')  # a unique tail of the name
    assert first.returncode == 0, first.stderr
    assert yaml.safe_load(first.stdout) == {'success': True, 'message': 'call 1'}
    second = run_tool('slam_call', '/cli_test_server/do_it')
    assert second.returncode == 1  # success: false
    assert yaml.safe_load(second.stdout) == {'success': False, 'message': 'call 2'}


def test_call_find_landmark_on_a_real_mapper(ros_harness: RosHarness, tmp_path: Path) -> None:
    mapper = ros_harness.start_process(
        'em_sam_mapper',
        ['em_sam_mapper', '--ros-args', '-p', f'report_dir:={tmp_path / "out"}'],
    )
    request = '{landmark_id: 7}'
    result = run_tool('slam_call', 'find_landmark', request, '--wait', '30')
    assert result.returncode == 1, result.stderr + mapper.log()  # found: false
    response = yaml.safe_load(result.stdout)
    assert response['found'] is False and response['sightings'] == []
    assert '7' in response['message']
    wrong = run_tool('slam_call', 'find_landmark', '{landmark: 7}')
    assert wrong.returncode == 2
    assert 'landmark is not a field of FindLandmark_Request' in wrong.stderr
    assert "did you mean 'landmark_id'?" in wrong.stderr
    bad_value = run_tool('slam_call', 'find_landmark', '{landmark_id: seven}')
    assert bad_value.returncode == 2
    assert "landmark_id: expected an integer (int32), got 'seven'" in bad_value.stderr
    assert mapper.stop() == 0, mapper.log()
