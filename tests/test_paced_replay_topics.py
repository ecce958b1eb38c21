"""Topic-level: paced replay (``slam_run --paced``) gives the result of the offline computation,
exactly, whatever the machine's load: the player publishes each message only once every node
has finished with what came before (slam_bringup.pacing), so no queue overflows and no
wall-clock timeout fires.

The EM-SAM graph (em_sam_office.yaml: odometry_ingest and em_sam_mapper, one process each)
plays bags/office_moveable.mcap paced. The keyframes the mapper ends with must be those of
OdometryIngest fed the same bag in the same order with the node's settings, every one (the
held-back last keyframes come out on the player's end-of-input, not on an idle timer); every
message the player published was taken, nothing was lost or dropped, and no wait for the
graph timed out.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from graph_checks import last_reports, offline_keyframes, run_graph

from slam_ros.qos import output_qos
from slam_ros.testing.harness import RosHarness

pytestmark = [pytest.mark.topic, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / 'bags' / 'office_moveable.mcap'
RUN_TIMEOUT_S = 400.0


def test_paced_replay_maps_every_keyframe_of_the_offline_computation(
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
            '--paced',
            '--exit-when-player-done',
        ],
        RUN_TIMEOUT_S,
    )
    assert status == 0, text
    assert 'paced (0 waits for the graph timed out)' in text, text

    expected = offline_keyframes(BAG)
    report = json.loads((tmp_path / 'out' / 'em_sam' / 'em_sam_report.json').read_text())
    assert report['trajectory']['stamps_ns'] == expected
    assert report['dropped_observations'] == 0
    assert report['observations_before_first_keyframe'] == 0

    last = last_reports(list(diagnostics.messages))
    player, ingest = last['/bag_player'], last['/odometry_ingest']
    mapper = last['/em_sam_mapper']
    assert int(player['paced timeouts']) == 0, player
    assert int(ingest['received odom']) == int(player['published /odom']), (ingest, player)
    assert int(ingest['lost odom']) == 0 and int(ingest['dropped']) == 0, ingest
    assert int(mapper['received odometry_increments']) == len(expected) - 1, mapper
    assert int(mapper['lost odometry_increments']) == 0 and int(mapper['dropped']) == 0
    assert int(mapper['received landmark_observations']) == int(
        player['published /landmark_observations']
    ), (mapper, player)
