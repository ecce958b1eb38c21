"""Topic-level, live and in real time: MonoSLAM + Shadow filter on the dynamic scene's camera.

``slam_run dynamic_scene_live.yaml --processes`` runs as users run it: ``dynamic_scene_sim``
(the scene of bags/dynamic_camera.mcap, published live at 30 Hz on the wall clock, unpaced),
``target_detector``, ``feature_tracker``, ``monoslam`` and ``shadow_filter``, one process
each. On two cores the image nodes cannot take every frame at 30 Hz: what they miss is lost
from their queues and counted on /diagnostics (``bench/live_keep_up.py`` measures how many).
Checked against /ground_truth/camera_pose at the same stamps, with the bounds of the bag
topic test (test_monoslam_topics.py): the camera centre over the first second, the median
and the largest error of every pose published; the pose is published through the whole run
(from the first second to the last) and tracking is never lost, however many frames the
machine's load made the nodes miss (the longest stretch without a pose is printed); every
image the camera published from the first one the tracker took was taken or counted lost.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from graph_checks import last_reports
from test_monoslam_topics import (
    MAX_ERROR_M,
    MAX_MEDIAN_ERROR_M,
    MAX_START_ERROR_M,
    START_FRAMES,
)

from slam_core.stamps import stamp_to_ns
from slam_ros.qos import output_qos
from slam_ros.testing.harness import Collector, RosHarness, wait_until

pytestmark = [pytest.mark.topic, pytest.mark.slow]

FRAMES = 300  # 10 s at 30 Hz (the graph's dynamic_scene_sim settings)
PERIOD_NS = round(1e9 / 30.0)
RENDER_TIMEOUT_S = 180.0  # the frames are rendered first: ~0.1 s each, on a busy machine
QUIET_S = 3.0  # no new pose for this long: the queued frames went through (a frame: < 0.2 s)
SETTLE_TIMEOUT_S = 120.0  # for that, however far behind the load put the pipeline


def position(pose: object) -> np.ndarray:
    p = pose.position  # type: ignore[attr-defined]
    return np.array([p.x, p.y, p.z])


def quiet(collector: Collector, quiet_s: float) -> bool:
    """Whether messages came, and none for ``quiet_s`` seconds."""
    received = list(collector.received_ns)
    return bool(received) and time.monotonic_ns() - received[-1] > quiet_s * 1e9


def test_monoslam_live_on_the_dynamic_scene(ros_harness: RosHarness, tmp_path: Path) -> None:
    harness = ros_harness
    diagnostics = harness.collect('/diagnostics', DiagnosticArray, output_qos(depth=100))
    poses = harness.collect('/monoslam/pose', PoseWithCovarianceStamped, output_qos(depth=100))
    truth = harness.collect('/ground_truth/camera_pose', PoseStamped, output_qos(depth=1000))
    run = harness.start_process(
        'slam_run',
        [sys.executable, '-m', 'slam_bringup.runner', 'dynamic_scene_live.yaml', '--processes'],
        cwd=tmp_path,
    )
    run.wait_for_line(RENDER_TIMEOUT_S, 'dynamic_scene_sim: all', 'frames done')
    wait_until(
        lambda: quiet(poses, QUIET_S),
        timeout_s=SETTLE_TIMEOUT_S,
        what='the last queued frames to go through',
    )
    assert run.process.poll() is None, run.log()
    run.stop(timeout_s=60.0)
    assert run.process.returncode == 0, run.log()

    true_at = {stamp_to_ns(m.header.stamp): position(m.pose) for m in truth.messages}
    first_ns = min(true_at)
    estimates = [(stamp_to_ns(m.header.stamp), position(m.pose.pose)) for m in poses.messages]
    assert estimates, run.log()
    frames = np.array([(stamp - first_ns) // PERIOD_NS for stamp, _ in estimates])
    errors = np.array([np.linalg.norm(p - true_at[stamp]) for stamp, p in estimates])
    start = errors[frames < START_FRAMES]
    assert start.size and start.max() < MAX_START_ERROR_M, start
    assert np.median(errors) < MAX_MEDIAN_ERROR_M and errors.max() < MAX_ERROR_M, errors
    assert frames[0] < START_FRAMES and frames[-1] >= FRAMES - START_FRAMES, frames

    last = last_reports(diagnostics.messages)
    camera, tracker, slam = last['/dynamic_scene_sim'], last['/feature_tracker'], last['/monoslam']
    published = int(camera['frames published'])
    assert published + int(camera['frames skipped']) == FRAMES, camera
    assert len(true_at) == published
    sent = published - int(tracker['first sequence image']) + 1
    assert int(tracker['received image']) + int(tracker['lost image']) == sent, tracker
    assert int(slam['lost']) == 0, slam  # tracking never lost
    print(  # noqa: T201
        f'live: {len(estimates)} poses for {published} frames published, tracker took '
        f'{tracker["received image"]} and lost {tracker["lost image"]}; error median '
        f'{np.median(errors):.3f} m, max {errors.max():.3f} m; longest without a pose '
        f'{np.diff(frames).max() * PERIOD_NS / 1e9:.2f} s'
    )
