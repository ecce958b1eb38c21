"""EM-SAM localization on a saved map: two office sessions, the paper's robot that returns.

Session 1 is mapped and saved as em_sam_node's map files; between the sessions three wall
markers are moved along their wall (``office_sim --relocated-static 3``); session 2 (another
seed: other desk moves, other noise) is localized on the saved map. Offline through the
processors for one seed, and as a user runs it: the bundled graph em_sam_localization.yaml
through slam_run, then ~/load_map on a running em_sam_mapper.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import PoseWithCovarianceStamped

from em_sam_node.core.em import run_em
from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.localization import localize, static_joint_covariance
from em_sam_node.mapper.map_files import known_map, read_map, write_map
from em_sam_node.offline import read_ground_truth, replay_bag, seen_at_both_positions
from slam_evaluation.em_sam_metrics import ate_rmse
from slam_interfaces.msg import MoveableLandmarkArray
from slam_ros.qos import latched_qos, output_qos
from slam_ros.testing.harness import RosHarness
from slam_sim.core.office import OfficeConfig, simulate_office
from slam_sim.office_bag import write_office_bag

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / 'bags' / 'office_moveable.mcap'  # seed 7
SESSION_2_SEED = 1007
GRAPH_TIMEOUT_S = 900.0


def expected_flags(seed: int) -> tuple[set[int], set[int]]:
    """The relocated wall markers of session 2 and every marker it must flag."""
    run = simulate_office(seed, config=OfficeConfig(relocated_static_count=3))
    return set(run.relocated_ids.tolist()), set(run.relocated_ids.tolist()) | set(
        run.seen_at_both_positions.tolist()
    )


@pytest.mark.slow
def test_two_office_sessions_offline(tmp_path: Path) -> None:
    """Seed 2 (its corridor-end marker 19 moves along the corridor: tested against its
    neighbours it shows, against the map's frame alone it did not)."""
    first = write_office_bag(simulate_office(2), tmp_path / 'session1').path
    first_data = replay_bag(first).data
    mapped = run_em(first_data, EmConfig(), record_snapshots=False)
    joint = static_joint_covariance(first_data, mapped)
    write_map(mapped, first_data.keyframe_stamps_ns, tmp_path / 'map', 'map', joint)
    saved = read_map(tmp_path / 'map')
    run = simulate_office(1002, config=OfficeConfig(relocated_static_count=3))
    second = write_office_bag(run, tmp_path / 'session2').path
    data = replay_bag(second).data
    truth = read_ground_truth(second)
    start = dataclasses.replace(data, prior_pose=saved.poses[0], prior_cov=np.eye(3) * 0.25)
    located, registration = localize(start, known_map(saved, tmp_path / 'map'), EmConfig())
    expected = set(run.relocated_ids.tolist()) | seen_at_both_positions(data, truth)
    assert set(located.landmark_ids[located.moveable].tolist()) == expected
    assert registration.consistent == 29 - 3
    true_xy = truth.poses_at(data.keyframe_stamps_ns)[:, :2]
    fresh = run_em(data, EmConfig(), record_snapshots=False)
    ate_located = ate_rmse(located.poses[:, :2], true_xy)
    ratio = ate_located / ate_rmse(fresh.poses[:, :2], true_xy)
    assert ratio <= 1.2, ratio  # this seed's saved map is better than session 2's own
    first_xy = read_ground_truth(first).poses_at(first_data.keyframe_stamps_ns)[:, :2]
    assert ate_located <= 1.1 * ate_rmse(mapped.poses[:, :2], first_xy)  # the map's accuracy


def run_graph(command: list[str], cwd: Path, harness: RosHarness, name: str) -> str:
    """Run a slam_run graph to its end in this test's domain; its log."""
    process = harness.start_process(name, command, cwd=cwd)
    try:
        code = process.process.wait(timeout=GRAPH_TIMEOUT_S)
    finally:
        process.stop()
    log = process.log()
    assert code == 0, log[-4000:]
    return log


@pytest.mark.topic
@pytest.mark.slow
def test_localization_graph_on_the_bundled_office_run(
    ros_harness: RosHarness, tmp_path: Path
) -> None:
    """Session 1: the bundled bag (seed 7) mapped and saved; session 2: seed 1007 with three
    wall markers moved, through the bundled localization graph."""
    # session 1's map as the mapping graph saves it beside its checkpoint (the graph itself:
    # test_em_sam_topics' test_save_map_writes_a_map_readable_without_numpy)
    first = replay_bag(BAG).data
    mapped = run_em(first, EmConfig(), record_snapshots=False)
    joint = static_joint_covariance(first, mapped)
    write_map(mapped, first.keyframe_stamps_ns, tmp_path / 'out' / 'em_sam', 'map', joint)
    session2 = tmp_path / 'out' / 'office_session2'
    simulated = subprocess.run(
        ['office_sim', '--seed', str(SESSION_2_SEED), '--relocated-static', '3',
         '--output', str(session2)],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert simulated.returncode == 0, simulated.stderr
    relocated, expected = expected_flags(SESSION_2_SEED)
    assert f'wall markers moved before the run {sorted(relocated)}' in simulated.stdout
    moveable = ros_harness.collect('/em_sam/moveable', MoveableLandmarkArray, latched_qos())
    poses = ros_harness.collect('/em_sam/pose', PoseWithCovarianceStamped, output_qos(100))
    log = run_graph(
        ['slam_run', 'em_sam_localization.yaml', '--bag', str(session2), '--paced'],
        tmp_path,
        ros_harness,
        'session2',
    )
    assert "localizing on 'out/em_sam/em_sam_map.yaml': 29 static landmarks" in log
    final = moveable.wait_for_count(1, timeout_s=30.0)[-1]
    assert {m.landmark_id for m in final.landmarks} == expected
    pose = poses.wait_for_count(1, timeout_s=30.0)[-1]
    assert pose.header.frame_id == 'map'
    planar = np.array(pose.pose.covariance).reshape(6, 6)[np.ix_([0, 1, 5], [0, 1, 5])]
    assert np.all(np.linalg.eigvalsh(planar) > 0)
    report = json.loads(
        (tmp_path / 'out' / 'em_sam_localization' / 'em_sam_report.json').read_text()
    )
    assert sorted(report['moveable_ids']) == sorted(expected)
    # its trajectory against the truth, next to a fresh map of the same session
    data = replay_bag(session2).data
    truth = read_ground_truth(session2)
    stamps = np.array(report['trajectory']['stamps_ns'], dtype=np.int64)
    located = np.array(report['trajectory']['poses'], dtype=float).reshape(-1, 3)
    fresh = run_em(data, EmConfig(), record_snapshots=False)
    ate_located = ate_rmse(located[:, :2], truth.poses_at(stamps)[:, :2])
    ate_fresh = ate_rmse(fresh.poses[:, :2], truth.poses_at(data.keyframe_stamps_ns)[:, :2])
    assert ate_located <= 1.2 * ate_fresh, (ate_located, ate_fresh)


@pytest.mark.topic
def test_load_map_service(ros_harness: RosHarness, tmp_path: Path) -> None:
    mapped = run_em(replay_bag(BAG).data, EmConfig(), record_snapshots=False)
    write_map(mapped, np.arange(len(mapped.poses)), tmp_path / 'map', 'map')
    mapper = ros_harness.start_process(
        'em_sam_mapper',
        ['em_sam_mapper', '--ros-args', '-p', f'report_dir:={tmp_path / "out"}'],
    )
    missing = subprocess.run(
        ['slam_call', 'load_map', f'{{map_file: {tmp_path / "nothing.yaml"}}}', '--wait', '30'],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert missing.returncode == 1, missing.stderr
    assert 'nothing.yaml' in missing.stdout and 'success: false' in missing.stdout
    loaded = subprocess.run(
        ['slam_call', 'load_map', f'{{map_file: {tmp_path / "map" / "em_sam_map.yaml"}}}'],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert loaded.returncode == 0, loaded.stdout + loaded.stderr
    answer = yaml.safe_load(loaded.stdout.split('---')[0])
    assert answer['success'] is True and answer['landmarks'] == 29
    assert 'localizing on' in answer['message']
    mapper.stop()
    assert 'Traceback' not in mapper.log()
