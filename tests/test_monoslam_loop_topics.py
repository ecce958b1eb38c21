"""Topic-level: MonoSLAM keeps its map around a loop and re-identifies it on images (issue 21;
paper 001: "when the camera perceives again the checkerboard, the features are re-matched
correctly, closing the loop").

A rendered loop bag is written to a temporary directory (the loop scene of
``monoslam_loop_evaluate``, seed 7, 20 s at 30 Hz: after 4 s the camera turns away from the
start area and the target for 6 s, then comes back to the view it left; eight moving
textured spheres) and replayed,
paced, into marker_detector, feature_tracker, monoslam and shadow_filter in this process,
wired as the monoslam_shadow graph wires them: monoslam publishes its predictions
(``features/predicted``: pixel, search ellipse and template warp of each map feature) and
the tracker uses them to follow its tracks and to search for the dropped ones (active
search). Paced: each image goes out once monoslam and shadow_filter have processed the one
before, and the tracker waits for each image's prediction (which then always comes), so the
result does not depend on spare CPU.

The truth comes from the bag's scene, re-rendered (``DynamicRenderer``), as the offline
evaluation takes it (``monoslam_loop_images``: world_points, projections, comebacks): a track's
world point
is where the ray through its first published pixel hits the scene; it is in view in an image
when it projects inside the image (past the tracker's border reach), in front of the camera
and short of the lens's fold, and nothing nearer lies along that pixel. A map feature of the
start area (published in the last second before the turn and in monoslam's map then) comes
back into view when it left it during the turn and is in view again after it; it is
*re-matched* when the tracker publishes it under its old id within 5 images of coming back,
within 3 px of where its world point projects, and it is still in monoslam's final map
(monoslam did not reject it as an outlier); published farther off, it is *wrong* (another
point under its id). The pose on monoslam/pose is compared with the bag's ground truth, and
its error over the last second with the measurement level's on the same scene and seed
(``monoslam_loop.run_loop``, variant (c): the issue's 1.5x).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from monoslam_graph import graph_parameters, tracker_noise
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, CompressedImage, PointCloud2

from marker_detector.detector.node import MarkerDetectorNode
from monoslam_shadow_node.common.core.tracking_noise import drift_bounded_offset_px
from monoslam_shadow_node.feature_tracker.node import FeatureTrackerNode
from monoslam_shadow_node.monoslam.conversions import POINT_DTYPE
from monoslam_shadow_node.monoslam.node import MonoSlamNode
from monoslam_shadow_node.monoslam.settings import PARAMETERS as MONOSLAM_PARAMETERS
from monoslam_shadow_node.shadow_filter.node import ShadowFilterNode
from slam_core.blas import single_threaded_blas
from slam_core.stamps import stamp_to_ns
from slam_evaluation.monoslam_loop import REMATCH_FRAMES, loop_frames, loop_scene, run_loop
from slam_evaluation.monoslam_loop_images import (
    REID_TOLERANCE_PX,
    comebacks,
    projections,
    world_points,
)
from slam_evaluation.monoslam_runs import Settings
from slam_interfaces.msg import FeatureTrackArray
from slam_ros.bag.source import BagSource
from slam_ros.qos import latched_qos, sensor_qos
from slam_ros.testing.harness import RosHarness, wait_until
from slam_sim.core.dynamic_render import DynamicRenderer
from slam_sim.dynamic_camera_bag import write_dynamic_camera_bag

pytestmark = [pytest.mark.topic, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
TARGET_CONFIG = ROOT / 'src' / 'monoslam_shadow_node' / 'config' / 'monoslam_dynamic_camera.yaml'


IMAGE_TOPIC = '/camera/image_raw/compressed'
INFO_TOPIC = '/camera/camera_info'
SEED = 7
AWAY_S = 6.0
SETTINGS = Settings((SEED,), 20.0, ('c',), ROOT / 'out' / 'unused')
SCENE = loop_scene(SETTINGS, True, AWAY_S)
PACE_TIMEOUT_S = 10.0  # per image; the four nodes share one executor thread
BORDER_REACH_PX = 10.5  # the tracker's: max(border_margin_px, lk_window_px / 2)
# Bounds, with what runs measured when they were set
MIN_PREDICTED_SHARE = 0.9  # images tracked with SLAM's prediction: 0.96 (none before SLAM starts)
# returning map features re-matched (the target: 0.6): 18 of 28 (0.64) with SLAM
# told the tracker's offsets as the graph tells it, 17-18 of 28 with white noise
MIN_REMATCHED_SHARE = 0.45
MAX_WRONG = 1  # re-identified at another point: 0 (1 with white noise: a look-alike 54 px off)
# last second's error against the measurement level's: 0.0097 m against 0.0126 m (0.77x;
# 1.45x with white noise); the far side's largest error 0.43 m (0.07 m with white noise)
MAX_FINAL_RATIO = 1.5


@pytest.fixture(scope='module', autouse=True)
def one_blas_thread() -> None:
    single_threaded_blas()


@dataclass
class LoopRun:
    """What the pipeline published, and the bag's stamps (K,) int ns in frame order."""

    stamps: list[int]
    features: dict[int, tuple[np.ndarray, np.ndarray]]  # stamp -> ids (N,), pixels (N, 2)
    poses: dict[int, np.ndarray]  # stamp -> camera centre (3,)
    maps: list[tuple[int, np.ndarray]]  # (stamp, POINT_DTYPE rows)
    predictions_used: int
    revived: int
    tracker_counts: dict[str, int]  # feature_tracker's /diagnostics counts at the end


def overrides(**parameters: Any) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in parameters.items()]


@pytest.fixture(scope='module')
def renderer() -> DynamicRenderer:
    return DynamicRenderer(SCENE, SEED)


@pytest.fixture(scope='module')
def loop_run(ros_context: None, tmp_path_factory: pytest.TempPathFactory) -> LoopRun:
    """Write the loop bag and play it through the four nodes once."""
    bag = tmp_path_factory.mktemp('loop') / 'loop.mcap'
    write_dynamic_camera_bag(SEED, bag, config=SCENE, single_file=True)
    harness = RosHarness(tmp_path_factory.mktemp('pipeline'))
    try:
        return play(harness, bag)
    finally:
        harness.close()


def play(harness: RosHarness, bag: Path) -> LoopRun:
    features = harness.collect('features', FeatureTrackArray)
    poses = harness.collect('monoslam/pose', PoseWithCovarianceStamped)
    maps = harness.collect('monoslam/map', PointCloud2, latched_qos())
    harness.add_node(
        MarkerDetectorNode(
            parameter_overrides=overrides(
                image_transport='compressed', marker_size_m=0.6, extrinsics_source='parameters'
            )
        )
    )
    tracker = FeatureTrackerNode(
        parameter_overrides=overrides(
            image_transport='compressed',
            use_predictions=True,
            # paced, each image's prediction comes: wait for it however busy the machine
            prediction_timeout_s=PACE_TIMEOUT_S,
        )
    )
    harness.add_node(tracker)
    target = {
        k: v for k, v in MONOSLAM_PARAMETERS.read_yaml(TARGET_CONFIG).items() if 'target' in k
    }
    slam = MonoSlamNode(
        parameter_overrides=overrides(
            **target, **tracker_noise('monoslam'), publish_predictions=True, map_period_s=0.1
        )
    )
    harness.add_node(slam)
    shadow = ShadowFilterNode(parameter_overrides=overrides(**tracker_noise('shadow_filter')))
    harness.add_node(shadow)
    publishers = {
        IMAGE_TOPIC: harness.publisher(IMAGE_TOPIC, CompressedImage, sensor_qos()),
        INFO_TOPIC: harness.publisher(INFO_TOPIC, CameraInfo, sensor_qos()),
    }
    for topic, count in ((IMAGE_TOPIC, 2), (INFO_TOPIC, 4)):
        harness.wait_for_subscribers(publishers[topic], count, timeout_s=20.0)
    stamps: list[int] = []
    with BagSource(bag) as source:
        for message in source.messages(list(publishers)):
            publishers[message.topic].publish(message.data)
            if message.topic != IMAGE_TOPIC:
                continue
            stamps.append(message.timestamp_ns)
            with contextlib.suppress(TimeoutError):  # a lost image shows in the counts
                wait_until(
                    lambda s=message.timestamp_ns: (
                        min(slam.sync.last_ns or 0, shadow.sync.last_ns or 0) >= s
                    ),
                    timeout_s=PACE_TIMEOUT_S,
                    what=f'monoslam and shadow_filter to process image {message.timestamp_ns} ns',
                )
    with contextlib.suppress(TimeoutError):
        wait_until(lambda: bool(poses.messages) and stamp_to_ns(
            poses.messages[-1].header.stamp) == stamps[-1], timeout_s=10.0)  # fmt: skip
    stats = tracker.processor.stats
    published = {
        stamp_to_ns(m.header.stamp): (
            np.array([t.id for t in m.tracks], np.int64),
            np.array([[t.u, t.v] for t in m.tracks], np.float64).reshape(-1, 2),
        )
        for m in features.messages
    }
    centres = {
        stamp_to_ns(m.header.stamp): np.array(
            [m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z]
        )
        for m in poses.messages
    }
    clouds = [
        (stamp_to_ns(m.header.stamp), np.frombuffer(bytes(m.data), POINT_DTYPE))
        for m in maps.messages
    ]
    return LoopRun(
        stamps, published, centres, clouds, stats.predictions_used, stats.revived,
        tracker.diagnostics_counts(),
    )  # fmt: skip


def active_ids(rows: np.ndarray) -> set[int]:
    """The ids of a monoslam/map cloud's points in the filter's state."""
    return {int(i) for i in rows['id'][rows['active'] != 0]}


def test_the_tracker_follows_slams_predictions(loop_run: LoopRun) -> None:
    assert loop_run.predictions_used >= MIN_PREDICTED_SHARE * len(loop_run.stamps)
    # /diagnostics says how many images went without their prediction (bench/live_keep_up),
    # read in one snapshot (the tracker may still be taking an image under load)
    counts = loop_run.tracker_counts
    assert counts['processed'] == counts['predictions used'] + counts['predictions missing']
    assert counts['predictions used'] >= MIN_PREDICTED_SHARE * len(loop_run.stamps)
    assert 'predictions late' in counts  # not a share of the missing: its image may be lost


def first_sightings(run: LoopRun) -> dict[int, tuple[int, np.ndarray]]:
    """Each published track's first image index and pixel."""
    first: dict[int, tuple[int, np.ndarray]] = {}
    for index, stamp in enumerate(run.stamps):
        ids, pixels = run.features.get(stamp, (np.zeros(0, np.int64), np.zeros((0, 2))))
        for track_id, pixel in zip(ids.tolist(), pixels, strict=True):
            first.setdefault(track_id, (index, pixel))
    return first


def test_returning_map_features_are_re_matched_at_their_points(
    loop_run: LoopRun, renderer: DynamicRenderer
) -> None:
    marks, rate, stamps = loop_frames(SCENE), round(SCENE.rate_hz), loop_run.stamps
    before = stamps[marks['start'] - rate : marks['start'] + 1]
    published = set().union(*(set(loop_run.features[s][0].tolist()) for s in before))
    in_map_then = [rows for stamp, rows in loop_run.maps if stamp <= stamps[marks['start']]]
    assert in_map_then, 'no map before the turn'
    mapped = published & active_ids(in_map_then[-1])
    final = active_ids(loop_run.maps[-1][1])
    points = world_points(renderer, first_sightings(loop_run), mapped)
    ids = sorted(points)
    visible, truth = projections(
        renderer, len(stamps), np.array([points[i] for i in ids]).reshape(-1, 3), BORDER_REACH_PX
    )
    returned = rematched = wrong = 0
    for column, entry in comebacks(visible, marks):
        track_id = ids[column]
        returned += 1
        for k in range(entry, min(entry + REMATCH_FRAMES + 1, len(stamps))):
            found, pixels = loop_run.features.get(stamps[k], (np.zeros(0, np.int64), None))
            if track_id not in found.tolist():
                continue
            assert pixels is not None
            pixel = pixels[found.tolist().index(track_id)]
            offset = float(np.linalg.norm(pixel - truth[k, column]))
            if offset > REID_TOLERANCE_PX:
                wrong += 1
                print(f'track {track_id} re-identified {offset:.1f} px from its point')  # noqa: T201
            elif track_id in final:
                rematched += 1
            break
    print(f'{rematched} of {returned} re-matched, {wrong} wrong')  # noqa: T201
    assert returned >= 10, f'only {returned} map features came back into view'
    assert wrong <= MAX_WRONG, f'{wrong} re-identified at another point'
    assert rematched >= MIN_REMATCHED_SHARE * returned, (
        f'{rematched} of {returned} returning map features re-matched '
        f'(tracker: {loop_run.revived} re-identified in all)'
    )


def test_the_loop_closes(loop_run: LoopRun, renderer: DynamicRenderer) -> None:
    marks, rate, stamps = loop_frames(SCENE), round(SCENE.rate_hz), loop_run.stamps
    errors = {}
    for index, stamp in enumerate(stamps):
        if stamp in loop_run.poses:
            errors[index] = float(np.linalg.norm(loop_run.poses[stamp] - renderer.pose(index)[1]))
    assert len(errors) >= 0.95 * len(stamps), f'{len(errors)} poses of {len(stamps)} images'
    far = [errors[k] for k in range(marks['away'], marks['return']) if k in errors]
    last = [errors[k] for k in range(len(stamps) - rate, len(stamps)) if k in errors]
    far_max, final = max(far), math.sqrt(float(np.mean(np.square(last))))
    print(f'far side max {far_max:.3f} m, last second {final:.4f} m RMS')  # noqa: T201
    measured = run_loop(SETTINGS, SEED, True, 'c', AWAY_S).metrics['last_second_rms_m']
    assert final <= MAX_FINAL_RATIO * measured, f'{final:.4f} m RMS, {measured:.4f} m measured'
    assert final <= 0.5 * far_max, f'{final:.3f} m after {far_max:.3f} m on the far side'


def test_the_graph_tells_slam_the_trackers_drift_bound() -> None:
    """The graph's declared tracker offsets follow its tracker's drift check (the two are
    set apart in the graph, so a change to one must reach the other); the Shadow filter keeps
    white noise (the graph's note)."""
    drift = graph_parameters('feature_tracker')['max_drift_px']
    assert drift > 0, 'the graph switched the drift check off: its offsets are unbounded'
    declared = graph_parameters('monoslam')['tracking_offset_px']
    assert declared == pytest.approx(drift_bounded_offset_px(drift))
    assert graph_parameters('shadow_filter')['tracking_offset_px'] == 0.0
