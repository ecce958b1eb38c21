"""The RViz configurations (src/slam_bringup/rviz/*.rviz) against the graphs they show.

Each (rviz file, graph) pair of ``PAIRS`` runs the graph for real (``slam_run``, a separate
process) on a short bag at a high rate, or for ``run_s`` seconds when it has no bag (a live
graph), while this process watches it as RViz would: it subscribes to every display's topic
with the display's QoS, asks DDS for the topic's publishers and their message types, and
records the TF tree on /tf and /tf_static. ``slam_bringup.rviz_config.check_rviz`` then
requires that every display's topic is published with the type the display takes and
received with its QoS, that the fixed frame is in the TF tree, and that every frame the 3D
displays' messages name joins the fixed frame (an Image display draws in its own panel and
needs no transform). The unit tests show that it fails on a tiny .rviz whose display names a
topic nobody publishes (and on the other problems).
"""

from __future__ import annotations

import importlib
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer

from slam_bringup.rviz_config import (
    GraphObservation,
    RvizConfigError,
    check_rviz,
    read_rviz,
)
from slam_ros.tf_tree import TfTree

ROOT = Path(__file__).resolve().parents[1]
RVIZ_DIR = ROOT / 'src' / 'slam_bringup' / 'rviz'
BAGS = ROOT / 'bags'
RUN_TIMEOUT_S = 120.0
POLL_S = 0.2


@dataclass(frozen=True)
class Pair:
    """An .rviz file and the graph it shows; the bag the graph plays (its first ``bag_s``
    seconds, at ``rate``), or None for a live graph, stopped after ``run_s`` seconds."""

    rviz: str
    graph: str
    fixed_frame: str
    bag: Path | None = None
    bag_s: float | None = None
    rate: float = 1.0
    run_s: float = 30.0


# em_sam_mapper solves every 10 s (wall clock): the run lasts at least 20 s
PAIRS = (
    Pair('em_sam.rviz', 'em_sam_office_camera.yaml', 'map', BAGS / 'office_camera.mcap', 80, 4),
    Pair('monoslam.rviz', 'monoslam_shadow.yaml', 'monoslam_map', BAGS / 'dynamic_camera.mcap'),
    # live: the simulated Peoplebot (its camera, odometry and TF on the wall clock)
    Pair('em_sam.rviz', 'peoplebot_sim_em_sam.yaml', 'map', run_s=30.0),
)


# --- the .rviz files, without ROS ---------------------------------------------------------


def test_every_rviz_file_is_paired_with_a_graph_and_reads() -> None:
    assert sorted(p.name for p in RVIZ_DIR.glob('*.rviz')) == sorted({p.rviz for p in PAIRS})
    for pair in PAIRS:
        needs = read_rviz(RVIZ_DIR / pair.rviz)
        assert needs.fixed_frame == pair.fixed_frame
        classes = {d.display_class for d in needs.displays}
        # map, path, camera image with overlays; the TF tree
        assert {
            'rviz_default_plugins/TF',
            'rviz_default_plugins/Path',
            'rviz_default_plugins/MarkerArray',
            'rviz_default_plugins/Image',
        } <= classes, (pair.rviz, classes)


def test_the_em_sam_file_shows_the_landmarks_and_the_moveable_sightings() -> None:
    text = (RVIZ_DIR / 'em_sam.rviz').read_text(encoding='utf-8')
    for namespace in ('static_landmarks', 'moveable_sightings', 'moveable_history', 'labels'):
        assert f'{namespace}: true' in text
    topics = read_rviz(RVIZ_DIR / 'em_sam.rviz').topics()
    assert topics['/em_sam/markers'].qos is not None
    assert topics['/em_sam/markers'].qos.durability == 'transient_local'  # the latched map


TINY_RVIZ = """\
Visualization Manager:
  Class: ""
  Displays:
    - Class: rviz_default_plugins/Grid
      Name: Grid
    - Class: rviz_common/Group
      Name: SLAM
      Displays:
        - Class: rviz_default_plugins/Path
          Name: Path
          Topic:
            Depth: 1
            Durability Policy: Transient Local
            History Policy: Keep Last
            Reliability Policy: Reliable
            Value: {topic}
    - Class: rviz_default_plugins/Image
      Name: Image
      Topic:
        Depth: 2
        Durability Policy: Volatile
        History Policy: Keep Last
        Reliability Policy: Best Effort
        Value: /camera/debug
  Global Options:
    Fixed Frame: {fixed_frame}
"""


def tiny(tmp_path: Path, topic: str = '/em_sam/path', fixed_frame: str = 'map') -> Path:
    path = tmp_path / 'tiny.rviz'
    path.write_text(TINY_RVIZ.format(topic=topic, fixed_frame=fixed_frame), encoding='utf-8')
    return path


def tf_message(*edges: tuple[str, str]) -> Any:
    """A TFMessage-like object with a transform per (parent, child)."""
    stamp = SimpleNamespace(sec=1, nanosec=0)
    return SimpleNamespace(
        transforms=[
            SimpleNamespace(
                header=SimpleNamespace(frame_id=parent, stamp=stamp), child_frame_id=child
            )
            for parent, child in edges
        ]
    )


def observation() -> GraphObservation:
    """A graph that publishes /em_sam/path (in map) and /camera/debug (camera_optical_frame),
    with map -> odom -> base_link -> camera_optical_frame and a separate 'elsewhere'."""
    tree = TfTree()
    tree.add(tf_message(('base_link', 'camera_optical_frame')), static=True)
    tree.add(tf_message(('map', 'odom'), ('odom', 'base_link')), static=False)
    tree.add(tf_message(('elsewhere', 'lost')), static=False)
    return GraphObservation(
        publishers={
            '/em_sam/path': {'nav_msgs/msg/Path'},
            '/camera/debug': {'sensor_msgs/msg/Image'},
        },
        frame_ids={'/em_sam/path': {'map'}, '/camera/debug': {'camera_optical_frame'}},
        received={'/em_sam/path': 3, '/camera/debug': 5},
        tree=tree,
    )


def test_the_tiny_rviz_reads_through_its_group(tmp_path: Path) -> None:
    needs = read_rviz(tiny(tmp_path))
    assert needs.fixed_frame == 'map'
    path, image = (needs.topics()[t] for t in ('/em_sam/path', '/camera/debug'))
    assert path.display_class == 'rviz_default_plugins/Path' and path.in_fixed_frame
    assert path.message_type == 'nav_msgs/msg/Path'
    assert path.qos is not None and path.qos.durability == 'transient_local'
    assert not image.in_fixed_frame and image.qos is not None
    assert image.qos.reliability == 'best_effort'
    assert check_rviz(needs, observation()) == []


def test_a_display_on_a_topic_nobody_publishes_fails(tmp_path: Path) -> None:
    problems = check_rviz(read_rviz(tiny(tmp_path, topic='/nobody/path')), observation())
    assert len(problems) == 1 and 'on /nobody/path: nobody publishes it' in problems[0]


def test_a_topic_of_another_type_fails(tmp_path: Path) -> None:
    seen = observation()
    seen.publishers['/em_sam/path'] = {'geometry_msgs/msg/PoseStamped'}
    problems = check_rviz(read_rviz(tiny(tmp_path)), seen)
    assert len(problems) == 1 and 'the display takes nav_msgs/msg/Path' in problems[0]


def test_a_display_that_receives_nothing_with_its_qos_fails(tmp_path: Path) -> None:
    seen = observation()
    seen.received['/em_sam/path'] = 0
    problems = check_rviz(read_rviz(tiny(tmp_path)), seen)
    assert len(problems) == 1 and 'nothing received' in problems[0]


def test_a_fixed_frame_not_in_the_tree_fails(tmp_path: Path) -> None:
    problems = check_rviz(read_rviz(tiny(tmp_path, fixed_frame='world')), observation())
    assert problems[0].startswith("fixed frame 'world' is not in the TF tree")
    # and the path's frame 'map' does not join 'world'
    assert len(problems) == 2 and "frame 'map' has no transform" in problems[1]


def test_a_message_frame_apart_from_the_fixed_frame_fails(tmp_path: Path) -> None:
    seen = observation()
    seen.frame_ids['/em_sam/path'] = {'map', 'lost'}
    seen.frame_ids['/camera/debug'] = {'lost'}  # an Image display needs no transform
    problems = check_rviz(read_rviz(tiny(tmp_path)), seen)
    assert len(problems) == 1 and "frame 'lost' has no transform" in problems[0]


def test_a_display_class_of_unknown_needs_is_refused(tmp_path: Path) -> None:
    path = tiny(tmp_path)
    path.write_text(
        path.read_text().replace('rviz_default_plugins/Image', 'rviz_default_plugins/Camera')
    )
    with pytest.raises(RvizConfigError, match='rviz_default_plugins/Camera'):
        read_rviz(path)
    path.write_text(TINY_RVIZ.format(topic='em_sam/path', fixed_frame='map'))
    with pytest.raises(RvizConfigError, match='not an absolute topic name'):
        read_rviz(path)


# --- the graphs, running ------------------------------------------------------------------


def message_class(type_name: str) -> type:
    package, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), name)


def header_frames(message: Any) -> set[str]:
    """The frame ids a display transforms: a MarkerArray's per marker (but DELETEALL's)."""
    markers = getattr(message, 'markers', None)
    if markers is not None:
        return {m.header.frame_id for m in markers if m.action != m.DELETEALL}
    return {message.header.frame_id}


def trim_bag(source: Path, target: Path, seconds: float) -> Path:
    """Write the first ``seconds`` of the bag ``source`` to the mcap bag ``target``."""
    with AnyReader([source]) as reader:
        writer = Writer(target, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        try:
            out = {
                c.id: writer.add_connection(
                    c.topic,
                    c.msgtype,
                    typestore=reader.typestore,
                    offered_qos_profiles=c.ext.offered_qos_profiles,
                )
                for c in reader.connections
            }
            stop = reader.start_time + round(seconds * 1e9)
            for connection, timestamp, raw in reader.messages(stop=stop):
                writer.write(out[connection.id], timestamp, raw)
        finally:
            writer.close()
    return target


def watch(harness: Any, needs: Any) -> GraphObservation:
    """Subscribe as the .rviz's displays and TF would; return the observation they fill."""
    from slam_ros.qos import latched_qos, output_qos

    seen = GraphObservation()
    for topic, display in needs.topics().items():
        seen.received[topic], seen.frame_ids[topic] = 0, set()

        def take(message: Any, topic: str = topic) -> None:
            seen.received[topic] += 1
            seen.frame_ids[topic] |= header_frames(message)

        harness.node.create_subscription(
            message_class(display.message_type), topic, take, display.qos.profile()
        )
    from tf2_msgs.msg import TFMessage

    harness.node.create_subscription(
        TFMessage, '/tf', lambda m: seen.tree.add(m, static=False), output_qos(depth=1000)
    )
    harness.node.create_subscription(
        TFMessage, '/tf_static', lambda m: seen.tree.add(m, static=True), latched_qos(depth=100)
    )
    return seen


def note_publishers(harness: Any, topics: list[str], seen: GraphObservation) -> None:
    for topic in topics:
        for info in harness.node.get_publishers_info_by_topic(topic):
            seen.publishers.setdefault(topic, set()).add(info.topic_type)


@pytest.mark.slow
@pytest.mark.topic
@pytest.mark.parametrize('pair', PAIRS, ids=[f'{p.rviz}-{p.graph}' for p in PAIRS])
def test_every_display_topic_and_frame_exists_in_its_graph(
    pair: Pair, ros_harness: Any, tmp_path: Path
) -> None:
    needs = read_rviz(RVIZ_DIR / pair.rviz)
    command = [sys.executable, '-m', 'slam_bringup.runner', pair.graph]
    if pair.bag is not None:
        assert pair.bag.exists(), (
            f'{pair.bag} is missing; restore it from git or see bags/README.md'
        )
        bag = pair.bag
        if pair.bag_s is not None:
            bag = trim_bag(pair.bag, tmp_path / 'short.mcap', pair.bag_s)
        command += ['--bag', str(bag), '--rate', str(pair.rate), '--exit-when-player-done']
    seen = watch(ros_harness, needs)
    run = ros_harness.start_process('slam_run', command)
    topics = list(needs.topics())
    started = time.monotonic()
    while run.process.poll() is None:
        note_publishers(ros_harness, topics, seen)
        elapsed = time.monotonic() - started
        if pair.bag is None and elapsed > pair.run_s:
            run.stop()
        assert elapsed < RUN_TIMEOUT_S, f'slam_run still running after {elapsed:.0f} s'
        time.sleep(POLL_S)
    assert run.process.returncode in (0, -2, 130), run.log()
    assert not seen.tree.conflicts, seen.tree.conflicts
    problems = check_rviz(needs, seen)
    assert not problems, '\n'.join(problems) + f'\npublishers: {seen.publishers}'
