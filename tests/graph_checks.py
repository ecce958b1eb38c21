"""What the topic tests of whole graphs check alike: the TF tree a listener saw, and each
node's last /diagnostics report."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message

from em_sam_node.odometry_ingest.conversions import odometry_pose
from em_sam_node.odometry_ingest.processor import IngestConfig, OdometryIngest
from slam_bringup.graph import load_graph
from slam_core.stamps import stamp_to_ns
from slam_interfaces.msg import LandmarkObservationArray
from slam_ros.bag.source import BagSource
from slam_ros.tf_tree import TfTree

# REP 105 with the office robot's camera: the one tree of the EM-SAM camera graphs
EM_SAM_CAMERA_TREE = {
    'odom': 'map',
    'base_link': 'odom',
    'camera_link': 'base_link',
    'camera_optical_frame': 'camera_link',
}


def tf_tree(tf_static: Iterable[Any], tf: Iterable[Any]) -> TfTree:
    """Return the tree of the /tf_static and /tf messages; assert no frame had two parents."""
    tree = TfTree()
    for message in list(tf_static):
        tree.add(message, static=True)
    for message in list(tf):
        tree.add(message, static=False)
    assert not tree.conflicts, tree.conflicts
    return tree


def parents(tree: TfTree) -> dict[str, str]:
    """Return each child frame's parent."""
    return {child: edge.parent for child, edge in tree.edges.items()}


def last_reports(arrays: Iterable[Any]) -> dict[str, dict[str, str]]:
    """Return each node's last /diagnostics values (DiagnosticArray messages, in order)."""
    last: dict[str, dict[str, str]] = {}
    for array in list(arrays):
        for status in array.status:
            last[status.name] = {value.key: value.value for value in status.values}
    return last


def run_graph(workdir: Path, arguments: list[str], timeout_s: float) -> tuple[int, str]:
    """Run ``slam_run ARGUMENTS`` in ``workdir`` (nodes write their reports relative to it)
    until it exits (killed after ``timeout_s``); return its exit status and its output."""
    log = workdir / 'slam_run.log'
    with log.open('wb') as output:
        process = subprocess.Popen(
            [sys.executable, '-m', 'slam_bringup.runner', *arguments],
            cwd=workdir, stdout=output, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env={**os.environ, 'PYTHONUNBUFFERED': '1'},
        )  # fmt: skip
        try:
            status = process.wait(timeout=timeout_s)
        finally:
            if process.poll() is None:
                process.kill()
    return status, log.read_text(errors='replace')


def graph_node_parameters(graph: Path, node: str, table: Any) -> dict[str, Any]:
    """Return ``node``'s parameters as ``graph`` sets them: ``table``'s (a ParamTable)
    defaults, then the entry's parameter files and inline values in order."""
    spec = next(spec for spec in load_graph(graph).nodes if spec.name == node)
    values = table.defaults()
    for source in spec.parameters:
        if isinstance(source, Path):
            values = table.read_yaml(source, values)
        else:
            values.update(source)
    return dict(values)


def offline_keyframes(bag: Path, *, observations: bool = True) -> list[int]:
    """The keyframe stamps of OdometryIngest (the node's defaults) over the bag's /odom and,
    with ``observations``, its /landmark_observations' stamps, in bag order."""
    ingest = OdometryIngest(IngestConfig())
    topics = ['/odom', '/landmark_observations'] if observations else ['/odom']
    increments = []
    with BagSource(bag) as source:
        for message in source.messages(topics):
            if message.topic == '/odom':
                stamp_ns, pose = odometry_pose(deserialize_message(message.data, Odometry))
                increments += ingest.add_odometry(stamp_ns, pose)
            else:
                array = deserialize_message(message.data, LandmarkObservationArray)
                stamp_ns = stamp_to_ns(array.header.stamp)
                increments += ingest.add_observation_stamp(stamp_ns, seen=bool(array.observations))
    increments += ingest.flush()
    return [increments[0].stamp_from_ns, *(i.stamp_to_ns for i in increments)]
