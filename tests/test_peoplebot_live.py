"""Topic-level, live and in real time: EM-SAM on the simulated Peoplebot.

``slam_run peoplebot_sim_em_sam.yaml --processes`` runs as users run it: ``peoplebot_sim``
(base and camera drivers in the office world, wall clock), ``route_driver`` on the paper's
office route, ``camera_mount`` on /tf_static, ``marker_detector``, ``odometry_ingest`` and
``em_sam_mapper``, one process each. After LIVE_S seconds of the route (office 1, the
corridor where the desk markers are moved, office 2) the graph is stopped with Ctrl-C and
the mapper writes its report (a final solve over everything it took). Checked:

- every moved marker that the detector saw at both positions (from what it published on
  /landmark_observations, split at the move on /ground_truth/landmarks) is flagged moveable,
  and no marker that stayed where it was;
- on /tf and /tf_static no frame ever has two parents, and from the first map -> odom on,
  map -> camera_optical_frame resolves at the stamp of every camera image up to the last odometry;
- the README's tools read the running graph as a user without the ROS CLI does:
  ``slam_echo em_sam/moveable --once``, ``slam_diag --once`` and ``slam_call find_landmark``
  for a moved marker, and their answers agree with the mapper's report;
- /diagnostics adds up: every image the simulator published from the first the detector
  took was taken or counted lost, the mapper lost no increment of the ingest's and dropped
  no sighting, and its first keyframe (the odometry connected) came within the discovery
  bound of the first sighting.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from graph_checks import EM_SAM_CAMERA_TREE, last_reports, parents, tf_tree
from sensor_msgs.msg import CameraInfo
from tf2_msgs.msg import TFMessage

from marker_detector.detector.node import HOLD_S
from slam_core.stamps import stamp_to_ns
from slam_interfaces.msg import LandmarkMap, LandmarkObservationArray
from slam_ros.qos import latched_qos, output_qos, sensor_qos
from slam_ros.testing.harness import RosHarness, wait_until

pytestmark = [pytest.mark.topic, pytest.mark.slow]

LIVE_S = 140.0  # the robot is in office 2 from about 90 s: most moved markers seen again
START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 120.0  # the mapper's final solve over ~1300 keyframes, on a busy machine


def seen_at_both_positions(
    observations: list[LandmarkObservationArray], truth: list[LandmarkMap]
) -> tuple[set[int], set[int], set[int]]:
    """Return (moved ids, moved ids observed before and after the move, ids never moved)."""
    assert len(truth) == 2, f'{len(truth)} ground-truth landmark maps (the start and the move)'
    before, after = (
        {m.landmark_id: (m.position.x, m.position.y) for m in t.landmarks} for t in truth
    )
    moved = {i for i in before if not np.allclose(before[i], after[i])}
    move_ns = stamp_to_ns(truth[1].header.stamp)
    seen: dict[bool, set[int]] = {False: set(), True: set()}
    for message in observations:
        is_after = stamp_to_ns(message.header.stamp) >= move_ns
        seen[is_after].update(o.landmark_id for o in message.observations)
    return moved, moved & seen[False] & seen[True], set(before) - moved


def run_tool(*command: str) -> subprocess.CompletedProcess[str]:
    """A command-line tool of the README, run to its end."""
    return subprocess.run(list(command), capture_output=True, text=True, timeout=120, check=False)


def user_tools(moved_ids: list[int]) -> dict[str, subprocess.CompletedProcess[str]]:
    """What the README's tools print about the running graph."""
    tools = {
        'echo': run_tool('slam_echo', 'em_sam/moveable', '--once', '--wait', '30'),
        # every node's 1 Hz report; the mapper's comes between its full passes, which take
        # seconds on a busy machine
        'diag': run_tool('slam_diag', '--once', '--wait', '30'),
    }
    if moved_ids:
        request = f'{{landmark_id: {moved_ids[0]}}}'
        tools['call'] = run_tool('slam_call', 'find_landmark', request, '--wait', '30')
    return tools


def check_user_tools(
    tools: dict[str, subprocess.CompletedProcess[str]], flagged: set[int]
) -> None:
    """The tools' answers agree with the mapper's final report (``flagged``)."""
    echo, diag = tools['echo'], tools['diag']
    assert echo.returncode == 0, echo.stderr
    moveable = yaml.safe_load(echo.stdout.split('---')[0])
    assert {landmark['landmark_id'] for landmark in moveable['landmarks']} <= flagged, moveable
    assert diag.returncode in (0, 1, 3), diag.stdout + diag.stderr  # something came
    names = {line.split()[1] for line in diag.stdout.splitlines()[1:-1]}
    assert {'/em_sam_mapper', '/odometry_ingest', '/marker_detector'} <= names, diag.stdout
    if 'call' in tools:
        call = tools['call']
        assert call.returncode == 0, call.stdout + call.stderr  # found: true
        assert yaml.safe_load(call.stdout)['sightings'], call.stdout


def test_em_sam_live_on_the_simulated_peoplebot(ros_harness: RosHarness, tmp_path: Path) -> None:
    harness = ros_harness
    diagnostics = harness.collect('/diagnostics', DiagnosticArray, output_qos(depth=100))
    tf = harness.collect('/tf', TFMessage, output_qos(depth=1000))
    tf_static = harness.collect('/tf_static', TFMessage, latched_qos(depth=100))
    infos = harness.collect('/camera/camera_info', CameraInfo, sensor_qos(depth=100))
    observations = harness.collect(
        '/landmark_observations', LandmarkObservationArray, output_qos(depth=1000)
    )
    truth = harness.collect('/ground_truth/landmarks', LandmarkMap, latched_qos(depth=10))
    run = harness.start_process(
        'slam_run',
        [sys.executable, '-m', 'slam_bringup.runner', 'peoplebot_sim_em_sam.yaml', '--processes'],
        cwd=tmp_path,
    )
    wait_until(lambda: len(infos) > 0, timeout_s=START_TIMEOUT_S, what='the first camera image')
    started = time.monotonic()
    wait_until(
        lambda: run.process.poll() is not None or time.monotonic() - started > LIVE_S,
        timeout_s=LIVE_S + 10.0,
        what=f'{LIVE_S:g} s of the route',
    )
    assert run.process.poll() is None, run.log()
    moved_now = seen_at_both_positions(list(observations.messages), list(truth.messages))[1]
    tools = user_tools(sorted(moved_now)[:1])  # while the graph runs, as a user would
    run.stop(timeout_s=STOP_TIMEOUT_S)
    assert run.process.returncode == 0, run.log()

    moved, seen_both, unmoved = seen_at_both_positions(
        list(observations.messages), list(truth.messages)
    )
    report = json.loads((tmp_path / 'out' / 'em_sam_live' / 'em_sam_report.json').read_text())
    flagged = set(report['moveable_ids'])
    assert len(moved) == 10 and len(seen_both) >= 5, (moved, seen_both)
    assert seen_both <= flagged, (
        f'seen at both positions {sorted(seen_both)}, flagged {sorted(flagged)}'
    )
    assert not flagged & unmoved, f'static markers flagged: {sorted(flagged & unmoved)}'
    check_user_tools(tools, flagged)

    tree = tf_tree(tf_static.messages, tf.messages)
    assert parents(tree) == EM_SAM_CAMERA_TREE
    map_odom = tree.edges['odom'].stamps
    # Ctrl-C stops the simulator between an image and the odometry after it: an image past
    # the last odom -> base_link is one tf2 would wait for in vain, not a gap in the tree.
    end = min(map_odom[-1], tree.edges['base_link'].stamps[-1])
    stamps = sorted(stamp_to_ns(message.header.stamp) for message in infos.messages)
    covered = [s for s in stamps if map_odom[0] <= s <= end]
    assert len(covered) >= 0.8 * len(stamps), f'{len(covered)} of {len(stamps)} images'
    unresolved = [s for s in covered if not tree.resolves('map', 'camera_optical_frame', s)]
    assert not unresolved, f'{len(unresolved)} of {len(covered)} images, first at {unresolved[0]}'

    last = last_reports(diagnostics.messages)
    sim, detector = last['/peoplebot_sim'], last['/marker_detector']
    ingest, mapper = last['/odometry_ingest'], last['/em_sam_mapper']
    received = int(detector['received image'])
    assert received == int(detector['processed']) + int(detector['dropped']) + int(
        detector['held']
    )
    sent = int(sim['frames published']) - int(detector['first sequence image']) + 1
    # the two nodes' last reports are up to a report period (1 s, 10 frames) apart, either
    # way round: beyond that, no frame went missing uncounted
    assert abs(sent - received - int(detector['lost image'])) <= 10, (sim, detector)
    assert int(detector['dropped']) == 0, detector
    # nothing lost between the ingest and the mapper (gaps in the ingest's sequence numbers
    # up to the last increment the mapper took). Their counts are not compared: live, each
    # node's last report is from its last second before Ctrl-C, the mapper's from before its
    # last solve (seconds, during which the ingest emits a keyframe per camera frame)
    assert int(mapper['lost odometry_increments']) == 0, mapper
    assert int(mapper['received odometry_increments']) > 1000, mapper
    assert int(ingest['lost odom']) == 0 and int(ingest['dropped']) == 0, ingest
    assert int(sim['commands rejected']) == 0, sim
    why = [line for line in run.log().splitlines() if 'WARN' in line and 'dropped' in line]
    assert int(mapper['dropped']) == 0, (mapper, ingest, why[:10])
    # Live, the odometry may connect (DDS discovery) after the first images were detected,
    # and each subscriber connects to the detector at its own time: what was published before
    # a subscriber connected never reached it (the 'lost' counts start at the first message
    # taken), so the sightings of the start cannot be accounted for from this test's side
    # (in CI it saw 59 before the first keyframe, the mapper 2; another run 20 and 48). What
    # holds: the map started, from the first odometry, within the discovery bound.
    first_keyframe = report['trajectory']['stamps_ns'][0]
    first_seen = min(stamp_to_ns(m.header.stamp) for m in observations.messages)
    assert first_keyframe - first_seen <= HOLD_S * 1e9, (first_seen, first_keyframe)
