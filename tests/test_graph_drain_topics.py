"""Topic-level: ``slam_run --processes`` lets the nodes work off their queued inputs before it
stops them, as one process does (real rclpy, the graph run as users run it).

The EM-SAM graph (em_sam_office.yaml) plays bags/office_moveable.mcap at a rate the nodes do
not keep up with on two cores: when the player has finished, inputs are still queued for
odometry_ingest and em_sam_mapper, and odometry_ingest holds back its last keyframes until
its input has been idle for a second. slam_run waits until every node has reported on
/diagnostics that it took no input for a while, and only then sends SIGINT. The nodes' last
reports then add up: every message the player published was taken or counted lost (under
load, from a full queue) by odometry_ingest, and every increment odometry_ingest published
was taken or counted lost by em_sam_mapper, from the first each took: nothing was left in a
queue at SIGINT. The player's own /diagnostics count what it published per topic. And the
mapper's report, written when it gets SIGINT, has the keyframes of its last /diagnostics
report: that report was the final one. (Stopped as soon as the player had
finished, the graph ended with about 350 of 1800 keyframes not mapped.)
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from graph_checks import last_reports, run_graph
from rosbags.highlevel import AnyReader

from slam_ros.qos import output_qos
from slam_ros.testing.harness import RosHarness

pytestmark = pytest.mark.topic

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / 'bags' / 'office_moveable.mcap'
RATE = 40.0
RUN_TIMEOUT_S = 240.0


def bag_count(bag: Path, topic: str) -> int:
    with AnyReader([bag]) as reader:
        return sum(c.msgcount for c in reader.connections if c.topic == topic)


def sent_from_first(total: int, report: dict[str, str], input: str) -> int:
    """What the publisher sent on ``input`` from the first message the node took on."""
    return total - int(report[f'first sequence {input}']) + 1


def test_processes_mode_drains_the_queues_before_stopping_the_nodes(
    ros_harness: RosHarness, tmp_path: Path
) -> None:
    assert BAG.is_file(), f'{BAG} is missing; restore it from git or see bags/README.md'
    diagnostics = ros_harness.collect('/diagnostics', DiagnosticArray, output_qos(depth=1000))
    status, text = run_graph(
        tmp_path,
        [
            'em_sam_office.yaml',
            '--processes',
            '--bag',
            str(BAG),
            '--rate',
            str(RATE),
            '--exit-when-player-done',
        ],
        RUN_TIMEOUT_S,
    )
    assert status == 0, text
    assert 'still busy' not in text, text

    last = last_reports(list(diagnostics.messages))
    assert set(last) >= {'/bag_player', '/odometry_ingest', '/em_sam_mapper'}, set(last)
    odometry_total = bag_count(BAG, '/odom')
    observations_total = bag_count(BAG, '/landmark_observations')
    player = last['/bag_player']
    assert int(player['published /odom']) == odometry_total, player
    assert int(player['published /landmark_observations']) == observations_total, player

    ingest = last['/odometry_ingest']
    taken = int(ingest['received odom']) + int(ingest['lost odom'])
    assert taken == sent_from_first(odometry_total, ingest, 'odom'), ingest
    mapper = last['/em_sam_mapper']
    increments = int(mapper['received odometry_increments'])
    taken = increments + int(mapper['lost odometry_increments'])
    assert taken == sent_from_first(int(ingest['increments']), mapper, 'odometry_increments'), (
        mapper,
        ingest,
    )
    taken = int(mapper['received landmark_observations']) + int(
        mapper['lost landmark_observations']
    )
    assert taken == sent_from_first(observations_total, mapper, 'landmark_observations'), mapper
    # the report the mapper wrote on SIGINT (solved again when SIGINT cut its last periodic
    # solve short, or it took inputs since) has the keyframes of its last /diagnostics
    # report: that report was its final one
    report = json.loads((tmp_path / 'out' / 'em_sam' / 'em_sam_report.json').read_text())
    assert report['num_keyframes'] == int(mapper['keyframes']), mapper
