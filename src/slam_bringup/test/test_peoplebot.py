"""The live Peoplebot GRAPHs: composed from config/peoplebot.yaml and validated, the drivers'
topics remapped onto the pipeline's, and the simulated one the same as the tested GRAPH."""

from __future__ import annotations

import ast
import itertools
from pathlib import Path

import pytest

from slam_bringup import peoplebot
from slam_bringup.graph import load_graph
from slam_bringup.graph_types import NodeSpec
from slam_bringup.peoplebot import CAMERAS, PIPELINES, ROBOTS, compose, main, write_graph

PACKAGE_DIR = Path(__file__).resolve().parents[1]

# What each driver publishes or takes, by its own (upstream) topic names, and the name our
# nodes use for it. p2os_driver: `pose`, `cmd_vel`; RosAria: `RosAria/pose`, `RosAria/cmd_vel`;
# usb_cam: `image_raw`, `image_raw/compressed`, `camera_info`; v4l2_camera: `image_raw`,
# `camera_info`; peoplebot_sim: ours.
DRIVER_TOPICS = {
    'peoplebot_sim': {
        'odom': '/odom',
        'cmd_vel': '/cmd_vel',
        'camera/image_raw': '/camera/image_raw',
    },
    'p2os_driver': {'pose': '/odom', 'cmd_vel': '/cmd_vel'},
    'RosAria': {'RosAria/pose': '/odom', 'RosAria/cmd_vel': '/cmd_vel'},
    'usb_cam': {'image_raw': '/camera/image_raw', 'camera_info': '/camera/camera_info'},
    'v4l2_camera': {'image_raw': '/camera/image_raw', 'camera_info': '/camera/camera_info'},
}


def resolved(node: NodeSpec, topic: str) -> str:
    """The topic a node in the root namespace uses for its relative ``topic``."""
    return dict(node.remappings).get(topic, '/' + topic if not topic.startswith('/') else topic)


VALID = [
    combination
    for combination in itertools.product(ROBOTS, CAMERAS, PIPELINES)
    if combination[1] != 'sim' or combination[0] == 'sim'
]


@pytest.mark.parametrize(('robot', 'camera', 'pipeline'), VALID)
def test_every_choice_gives_a_valid_graph_wired_to_our_topics(
    robot: str, camera: str, pipeline: str, tmp_path: Path
) -> None:
    graph = write_graph(tmp_path / 'g.yaml', robot, camera, pipeline)
    names = [node.name for node in graph.nodes]
    assert len(names) == len(set(names))
    assert 'camera_mount' in names
    drivers = [node for node in graph.nodes if node.name in DRIVER_TOPICS]
    assert len(drivers) == (1 if camera == 'sim' else 2)
    for driver in drivers:
        for own, ours in DRIVER_TOPICS[driver.name].items():
            assert resolved(driver, own) == ours, (driver.name, own)
    if pipeline in ('em_sam', 'both'):
        assert {'marker_detector', 'odometry_ingest', 'em_sam_mapper'} <= set(names)
    if pipeline in ('monoslam', 'both'):
        assert {'target_detector', 'feature_tracker', 'monoslam', 'shadow_filter'} <= set(names)
        target = next(n for n in graph.nodes if n.name == 'target_detector')
        slam = next(n for n in graph.nodes if n.name == 'monoslam')
        # the target's fiducials reach monoslam and its observations never reach EM-SAM
        assert resolved(target, 'fiducials') == resolved(slam, 'fiducials') != '/fiducials'
        assert resolved(target, 'landmark_observations') != '/landmark_observations'


def test_the_parts_split_the_graph_between_robot_and_laptop(tmp_path: Path) -> None:
    whole = write_graph(tmp_path / 'all.yaml', 'p2os', 'usb_cam', 'both')
    robot = write_graph(tmp_path / 'r.yaml', 'p2os', 'usb_cam', 'both', part='drivers')
    laptop = write_graph(tmp_path / 'l.yaml', 'p2os', 'usb_cam', 'both', part='pipeline')
    assert [n.name for n in robot.nodes] == ['p2os_driver', 'usb_cam', 'camera_mount']
    assert [n.name for n in robot.nodes + laptop.nodes] == [n.name for n in whole.nodes]


def test_wrong_choices_are_named() -> None:
    with pytest.raises(ValueError, match="robot 'turtlebot': choose one of sim, p2os, rosaria"):
        compose('turtlebot', 'sim', 'em_sam')
    with pytest.raises(ValueError, match="camera 'sim' is the simulated robot's own camera"):
        compose('p2os', 'sim', 'em_sam')
    with pytest.raises(ValueError, match='pipeline'):
        compose('sim', 'sim', 'orb_slam')
    with pytest.raises(ValueError, match="part 'half'"):
        compose('sim', 'sim', 'em_sam', part='half')


def test_the_simulated_graph_is_the_tested_one(tmp_path: Path) -> None:
    composed = write_graph(tmp_path / 'g.yaml', 'sim', 'sim', 'em_sam')
    tested = load_graph(PACKAGE_DIR / 'graphs' / 'peoplebot_sim_em_sam.yaml')

    def entries(graph: object) -> list[tuple[object, ...]]:
        return [
            (n.name, n.package, n.executable, n.plugin, n.parameters, n.remappings)
            for n in graph.nodes  # type: ignore[attr-defined]
        ]

    assert entries(composed) == entries(tested)


def test_the_command_line_writes_a_graph_and_refuses_a_bad_choice(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    output = tmp_path / 'robot.yaml'
    assert main(['--robot', 'rosaria', '--camera', 'usb_cam', '-o', str(output)]) == 0
    assert 'RosAria' in output.read_text() and 'slam_run' in capsys.readouterr().out
    with pytest.raises(SystemExit) as raised:
        main(['--robot', 'p2os', '--camera', 'sim', '-o', str(output)])
    assert raised.value.code == 2
    assert "camera 'sim'" in capsys.readouterr().err


def test_the_launch_file_takes_its_choices_and_graph_from_the_module() -> None:
    """The launch file cannot be run here (no launch_ros); check what it takes from us."""
    tree = ast.parse((PACKAGE_DIR / 'launch' / 'peoplebot.launch.py').read_text())
    imported = {
        alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.module == 'slam_bringup.peoplebot'
        for alias in node.names
    }
    assert imported == {'CAMERAS', 'PIPELINES', 'ROBOTS', 'write_graph'}
    assert all(hasattr(peoplebot, name) for name in imported)
    source = ast.unparse(tree)
    for argument in ('robot', 'camera', 'pipeline', 'rviz'):
        assert f"DeclareLaunchArgument('{argument}'" in source
    assert all((PACKAGE_DIR / 'rviz' / f'{v}.rviz').is_file() for v in ('em_sam', 'monoslam'))
