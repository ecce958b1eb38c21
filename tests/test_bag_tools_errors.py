"""Bad input to the bag tools: one line naming the culprit, exit code 2, no traceback."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from bag_fixtures import tool_env
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_types_from_msg

from slam_ros.testing.messages import RELIABLE_QOS, BagTopic, write_bag
from slam_ros.typesys import TypeRegistry

ODOM = (BagTopic('/odom', 'nav_msgs/msg/Odometry', 50.0),)


def run_tool(*command: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        list(command),
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=tool_env(),
        check=False,
    )


def assert_one_line_error(result: subprocess.CompletedProcess[str], *culprits: str) -> str:
    """Exit 2, exactly one 'error:' line on stderr naming every culprit, no traceback."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert 'Traceback' not in result.stderr
    errors = [line for line in result.stderr.splitlines() if ': error: ' in line]
    assert len(errors) == 1, result.stderr
    for culprit in culprits:
        assert culprit in errors[0], (culprit, errors[0])
    return errors[0]


@pytest.fixture
def odom_bag(tmp_path: Path) -> Path:
    write_bag(tmp_path / 'odom', ODOM, duration_s=4.0, seed=11)
    return tmp_path / 'odom'


def mcap_file(bag: Path) -> Path:
    (path,) = bag.glob('*.mcap')
    return path


@pytest.mark.parametrize('tool', ['bag_player', 'bag_info'])
def test_missing_bag_is_named(tool: str, tmp_path: Path) -> None:
    missing = tmp_path / 'no_such_bag.mcap'
    assert_one_line_error(run_tool(tool, str(missing)), str(missing), 'does not exist')


@pytest.mark.parametrize('tool', ['bag_player', 'bag_info'])
def test_truncated_mcap_is_named(tool: str, odom_bag: Path) -> None:
    path = mcap_file(odom_bag)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 6 // 10])
    assert_one_line_error(
        run_tool(tool, str(path), '--rate', '20')
        if tool == 'bag_player'
        else run_tool(tool, str(path)),
        str(path),
    )


def test_corrupt_payload_is_named_during_playback(odom_bag: Path) -> None:
    path = mcap_file(odom_bag)
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 4096] = b'\xff' * 4096  # lengths of strings and records blow up
    path.write_bytes(bytes(data))
    line = assert_one_line_error(run_tool('bag_player', str(path), '--rate', '20'), str(path))
    assert 'corrupt' in line


def test_garbage_file_is_named(tmp_path: Path) -> None:
    path = tmp_path / 'garbage.mcap'
    path.write_bytes(b'this is not a bag' * 100)
    assert_one_line_error(run_tool('bag_info', str(path)), str(path))


def test_directory_without_bag_is_named(tmp_path: Path) -> None:
    empty = tmp_path / 'empty_dir'
    empty.mkdir()
    assert_one_line_error(run_tool('bag_player', str(empty)), str(empty))


def write_unknown_type_bag(path: Path) -> None:
    registry = TypeRegistry()
    definition = 'int32 gear\nstring label\n'
    registry.typestore.register(get_types_from_msg(definition, 'widget_msgs/msg/Widget'))
    widget = registry.typestore.types['widget_msgs/msg/Widget'](gear=3, label='x')
    msgdef, rihs01 = registry.msgdef_and_hash('nav_msgs/msg/Odometry')
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        widgets = writer.add_connection(
            '/widgets',
            'widget_msgs/msg/Widget',
            typestore=registry.typestore,
            offered_qos_profiles=[RELIABLE_QOS],
        )
        writer.add_connection(
            '/odom',
            'nav_msgs/msg/Odometry',
            msgdef=msgdef,
            rihs01=rihs01,
            offered_qos_profiles=[RELIABLE_QOS],
        )
        for i in range(3):
            writer.write(
                widgets,
                10**9 + i,
                registry.typestore.serialize_cdr(widget, 'widget_msgs/msg/Widget'),
            )


def test_topic_without_type_definition_is_named(tmp_path: Path) -> None:
    write_unknown_type_bag(tmp_path / 'widgets')
    line = assert_one_line_error(
        run_tool('bag_player', str(tmp_path / 'widgets')), "'/widgets'", 'widget_msgs/msg/Widget'
    )
    assert 'no definition' in line
    # Leaving the topic out plays the rest.
    result = run_tool('bag_player', str(tmp_path / 'widgets'), '--topics', '/odom')
    assert result.returncode == 0, result.stderr


def test_unknown_topic_selection_is_named(odom_bag: Path) -> None:
    assert_one_line_error(
        run_tool('bag_player', str(odom_bag), '--topics', '/nope'), "'/nope'", 'topics'
    )


@pytest.mark.parametrize(
    ('option', 'value', 'parameter'),
    [
        ('--rate', '0', 'rate'),
        ('--rate', 'nan', 'rate'),
        ('--start-offset', '-1', 'start_offset_s'),
        ('--clock-hz', '-5', 'clock_hz'),
    ],
)
def test_invalid_player_option_names_parameter(
    odom_bag: Path, option: str, value: str, parameter: str
) -> None:
    assert_one_line_error(run_tool('bag_player', str(odom_bag), option, value), parameter)


def test_a_start_offset_beyond_the_bag_is_refused(odom_bag: Path) -> None:
    line = assert_one_line_error(
        run_tool('bag_player', str(odom_bag), '--start-offset', '9999'), 'start_offset_s=9999'
    )
    assert 'beyond the end' in line and str(odom_bag) in line


def test_invalid_parameter_file_value_names_parameter(odom_bag: Path, tmp_path: Path) -> None:
    params = tmp_path / 'player.yaml'
    params.write_text(f'/**:\n  ros__parameters:\n    bag_path: {odom_bag}\n    rate: fast\n')
    result = run_tool('bag_player', '--ros-args', '--params-file', str(params))
    assert_one_line_error(result, 'rate')


def test_recorder_refuses_existing_output(odom_bag: Path) -> None:
    assert_one_line_error(
        run_tool('bag_recorder', '-a', '-o', str(odom_bag)), str(odom_bag), 'exists'
    )
