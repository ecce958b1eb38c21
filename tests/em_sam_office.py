"""The office bag (bags/office_moveable.mcap, seed 7) played paced through odometry_ingest and
em_sam_mapper, for the topic tests: 29 static wall markers and 10 desk markers (ids 100-109)
that move from office 1 to office 2 while the robot is in the corridor."""

from __future__ import annotations

from pathlib import Path

import pytest
from rclpy.parameter import Parameter

from em_sam_node.mapper.node import EmSamMapperNode
from em_sam_node.odometry_ingest.node import OdometryIngestNode
from slam_bringup.bag_player import BagPlayerNode
from slam_ros.progress import PACED_ENV
from slam_ros.testing.harness import RosHarness, wait_until

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'office_moveable.mcap'
MOVED = set(range(100, 110))


def call(
    harness: RosHarness, service_type: type, name: str, request: object, timeout_s: float = 60.0
) -> object:
    client = harness.node.create_client(service_type, name)
    assert client.wait_for_service(timeout_sec=timeout_s), name
    future = client.call_async(request)
    wait_until(future.done, timeout_s=timeout_s, what=f'the reply of {name}')
    return future.result()


def play_office(
    harness: RosHarness, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, *, online: bool = True
) -> tuple[OdometryIngestNode, EmSamMapperNode]:
    """Play the office bag paced (slam_ros.progress: each message once both nodes are done
    with the last, whatever the machine's load) through odometry_ingest and em_sam_mapper."""
    monkeypatch.setenv(PACED_ENV, '1')  # the nodes report their progress
    ingest = harness.add_node(OdometryIngestNode())
    mapper = harness.add_node(
        EmSamMapperNode(
            parameter_overrides=[
                Parameter('optimize_period_s', value=0.0),
                Parameter('report_dir', value=str(tmp_path / 'report')),
                Parameter('online', value=online),
            ]
        )
    )
    player = harness.add_node(
        BagPlayerNode(
            parameter_overrides=[
                Parameter('bag_path', value=str(BAG)),
                Parameter('paced', value=True),
                Parameter('paced_nodes', value=['/odometry_ingest', '/em_sam_mapper']),
                Parameter('topics', value=['/odom', '/landmark_observations']),
                Parameter(
                    'remap', value=['/odom:=odom', '/landmark_observations:=landmark_observations']
                ),
                Parameter('wait_for_subscribers_s', value=20.0),
            ]
        )
    )
    assert player.finished.wait(240) and player.error is None
    assert player.paced_timeouts == 0  # every message waited for the graph
    wait_until(lambda: ingest.flushed, timeout_s=20, what='odometry_ingest to flush')
    return ingest, mapper
