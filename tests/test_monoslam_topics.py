"""Topic-level: MonoSLAM with the Shadow filter on the simulated dynamic scene (real rclpy).

The pipeline: bags/dynamic_camera.mcap (seed 0, 10 s, 300 JPEG frames at 30 Hz, a hand-held
camera in a room with four moving textured spheres and the initialization target, AprilTag
36h11 id 0 with a 0.6 m square) is replayed, each image once monoslam has processed the one
before (paced, so the result does not depend on spare CPU), into marker_detector,
feature_tracker, monoslam (initialize=handover, the target's pose from
config/monoslam_dynamic_camera.yaml) and shadow_filter (its defaults), both told the feature
tracker's noise as the monoslam_shadow graph declares it (``monoslam_graph``), all in this
process. monoslam/pose is compared with
/ground_truth/camera_pose, and the statuses on shadow/tracks and shadow/static_features with
/ground_truth/labels sampled at each track's pixel in the same image.

Then bad inputs to a monoslam node started as a process (its log is read back), made from
slam_sim's measurement-level dynamic scene (true target corners, noisy features): features
before any camera_info, no target in view, NaN pixels, out-of-order stamps, handovers that
are NaN, not STATIC or in another frame, a changed and an unusable camera_info, features
without fiducials, every feature and the target lost (tracking lost, then re-initialized
when the target returns), the trajectory file written on SIGINT; and invalid parameters.
Nothing published is ever NaN.

The nodes' matrices are small: OpenBLAS is limited to one thread (its threads spin against
each other on a shared 2-core machine).
"""

from __future__ import annotations

import contextlib
import math
import signal
import sys
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from bag_fixtures import invalid_parameter_error, tool_env
from geometry_msgs.msg import PoseWithCovarianceStamped
from monoslam_graph import tracker_noise
from nav_msgs.msg import Path as PathMessage
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, CompressedImage, PointCloud2
from tf2_msgs.msg import TFMessage

from marker_detector.detector.node import MarkerDetectorNode
from monoslam_shadow_node.feature_tracker.node import FeatureTrackerNode
from monoslam_shadow_node.monoslam.conversions import POINT_DTYPE
from monoslam_shadow_node.monoslam.node import MonoSlamNode
from monoslam_shadow_node.monoslam.settings import PARAMETERS as MONOSLAM_PARAMETERS
from monoslam_shadow_node.shadow_filter.node import ShadowFilterNode
from slam_core.blas import single_threaded_blas
from slam_core.stamps import ns_to_stamp, stamp_to_ns
from slam_interfaces.msg import (
    FeatureTrack,
    FeatureTrackArray,
    FiducialArray,
    FiducialDetection,
    ShadowTrack,
    ShadowTrackArray,
)
from slam_ros.bag.source import BagSource
from slam_ros.qos import latched_qos, sensor_qos
from slam_ros.testing.harness import NodeProcess, RosHarness, wait_until
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import DynamicSceneRun, simulate_dynamic_scene
from slam_sim.core.init_target import InitTarget, target_pixels

pytestmark = [pytest.mark.topic, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / 'bags' / 'dynamic_camera.mcap'
TARGET_CONFIG = ROOT / 'src' / 'monoslam_shadow_node' / 'config' / 'monoslam_dynamic_camera.yaml'
MODULE = 'monoslam_shadow_node.monoslam.node'
IMAGE_TOPIC = '/camera/image_raw/compressed'
INFO_TOPIC = '/camera/camera_info'
PACE_TIMEOUT_S = 10.0  # per image; the four nodes share one executor thread
LOG_TIMEOUT_S = 15.0
LABEL_STATIC, FIRST_OBJECT_LABEL = 1, 2
START_FRAMES = 30
# Bounds on the pipeline run, with what two runs measured when they were set
# (after the tracker's drift check; before it, handed-over features that slid along
# occluding edges made the pose drift to 0.40-0.50 m median, 0.65-0.72 m max).
MIN_POSES = 270  # poses published of 300 images: 297, 298 (best-effort images drop)
MAX_START_ERROR_M = 0.06  # camera centre error over the first second (the target): 0.032
MAX_MEDIAN_ERROR_M = 0.1  # median over all poses: 0.032, 0.033
MAX_ERROR_M = 0.2  # and largest: 0.060, 0.060
MIN_HANDOVERS = 200  # features handed over: 380, 380
DELIVERY_TIMEOUT_S = 10.0  # the last outputs, once monoslam processed the last image
MIN_SHADOW_SHARE = 0.95  # images the Shadow filter processed (issue 20): 299 of 300
MIN_HANDED_FEATURES = 100  # distinct features handed over (issue 20): 387
MIN_STATIC_SHARE = 0.95  # of them seen on static surfaces when handed over: 0.987, 0.987
# DYNAMIC share of the Shadow filter's sightings on objects: 0.42, 0.42 (0.87 before the drift
# check: it also ends tracks on the textured spheres as they turn and grow, so more of them
# end while still PENDING)
MIN_OBJECT_RECALL = 0.3
# The object share of DYNAMIC sightings, against their share among all sightings (0.066):
# 21.8 times, 21.8 (5 before the drift check)
MIN_DYNAMIC_ENRICHMENT = 10.0


@pytest.fixture(scope='module', autouse=True)
def one_blas_thread() -> None:
    single_threaded_blas()


# --- the pipeline on the simulated bag -----------------------------------------------------


@dataclass
class Truth:
    """The bag's ground truth: optical centre (3,) m and label image per image stamp."""

    centres: dict[int, np.ndarray]
    labels: dict[int, np.ndarray]
    last_stamp_ns: int
    pixels: dict[int, dict[int, tuple[float, float]]] = field(default_factory=dict)


@dataclass
class PipelineRun:
    """What the pipeline published, by topic."""

    poses: list[PoseWithCovarianceStamped]
    features: list[FeatureTrackArray]
    tracks: list[ShadowTrackArray]
    handovers: list[ShadowTrackArray]
    maps: list[PointCloud2]
    paths: list[PathMessage]
    transforms: list[TFMessage]
    unpaced: list[int]
    """Stamps (int ns) of images monoslam had not processed after PACE_TIMEOUT_S."""
    links: tuple[int, int]
    """Poses the shadow_filter took with and without their monoslam/pose/link."""


def read_truth() -> Truth:
    # the sample bag is part of the repository: without it the checkout is broken (fail)
    assert BAG.exists(), f'{BAG} is missing; restore it from git or see bags/README.md'
    centres: dict[int, np.ndarray] = {}
    labels: dict[int, np.ndarray] = {}
    with BagSource(BAG) as bag:
        topics = ['/ground_truth/camera_pose', '/ground_truth/labels']
        for message in bag.messages(topics):
            decoded: Any = bag.typestore.deserialize_cdr(message.data, message.msgtype)
            stamp_ns = stamp_to_ns(decoded.header.stamp)
            if message.topic == topics[0]:
                p = decoded.pose.position
                centres[stamp_ns] = np.array([p.x, p.y, p.z])
            else:
                png = np.frombuffer(bytes(decoded.data), np.uint8)
                image = cv2.imdecode(png, cv2.IMREAD_UNCHANGED)
                if image is None:
                    raise ValueError(f'{BAG}: label image at stamp {stamp_ns} ns is not a PNG')
                labels[stamp_ns] = image
    return Truth(centres, labels, max(centres))


def overrides(**parameters: Any) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in parameters.items()]


@pytest.fixture(scope='module')
def truth() -> Truth:
    return read_truth()


@pytest.fixture(scope='module')
def pipeline(
    ros_context: None, tmp_path_factory: pytest.TempPathFactory, truth: Truth
) -> PipelineRun:
    """Play the bag through the four nodes once; return what they published (the nodes are
    gone by then: the other tests use the same topics)."""
    harness = RosHarness(tmp_path_factory.mktemp('pipeline'))
    try:
        return play(harness, truth)
    finally:
        harness.close()


def play(harness: RosHarness, truth: Truth) -> PipelineRun:
    collectors = {
        'poses': harness.collect('monoslam/pose', PoseWithCovarianceStamped),
        'features': harness.collect('features', FeatureTrackArray),
        'tracks': harness.collect('shadow/tracks', ShadowTrackArray),
        'handovers': harness.collect('shadow/static_features', ShadowTrackArray),
        'maps': harness.collect('monoslam/map', PointCloud2, latched_qos()),
        'paths': harness.collect('monoslam/path', PathMessage),
        'transforms': harness.collect('/tf', TFMessage),
    }
    harness.add_node(
        MarkerDetectorNode(
            parameter_overrides=overrides(
                image_transport='compressed', marker_size_m=0.6, extrinsics_source='parameters'
            )
        )
    )
    harness.add_node(
        FeatureTrackerNode(parameter_overrides=overrides(image_transport='compressed'))
    )
    target = {
        k: v for k, v in MONOSLAM_PARAMETERS.read_yaml(TARGET_CONFIG).items() if 'target' in k
    }
    slam = MonoSlamNode(
        parameter_overrides=overrides(**target, **tracker_noise('monoslam'), publish_tf=True)
    )
    shadow = ShadowFilterNode(parameter_overrides=overrides(**tracker_noise('shadow_filter')))
    for node in (slam, shadow):
        harness.add_node(node)
    unpaced = pace(harness, slam)
    last = truth.last_stamp_ns
    wait_until(lambda: slam.sync.last_ns == last, what='monoslam to process the last image')
    wait_until(lambda: shadow.sync.last_ns == last, what='shadow_filter to take the last image')

    def delivered() -> bool:  # the last pose and its path have come through (separate topics)
        poses, paths = collectors['poses'].messages, collectors['paths'].messages
        return bool(poses and paths) and (
            stamp_to_ns(poses[-1].header.stamp) == last
            and paths[-1].poses[-1].header.stamp == poses[-1].header.stamp
        )

    # not delivered (e.g. not tracking in the last image): the tests below say what is missing
    with contextlib.suppress(TimeoutError):
        wait_until(delivered, timeout_s=DELIVERY_TIMEOUT_S, what='the last pose and path')
    messages = {name: list(c.messages) for name, c in collectors.items()}
    counts = shadow.diagnostics_counts()
    links = (counts['poses linked'], counts['poses unlinked'])
    return PipelineRun(**messages, unpaced=unpaced, links=links)


def pace(harness: RosHarness, slam: MonoSlamNode) -> list[int]:
    """Replay the bag's camera topics (raw CDR, bag order), each image only once monoslam has
    processed the one before, so that the result does not depend on spare CPU; an image that
    does not come through (best-effort delivery) is waited for PACE_TIMEOUT_S, then passed.
    Return the stamps (int ns) of the images passed that way."""
    publishers = {
        IMAGE_TOPIC: harness.publisher(IMAGE_TOPIC, CompressedImage, sensor_qos()),
        INFO_TOPIC: harness.publisher(INFO_TOPIC, CameraInfo, sensor_qos()),
    }
    # images: marker_detector and feature_tracker; camera_info: those and the two filters
    for topic, count in ((IMAGE_TOPIC, 2), (INFO_TOPIC, 4)):
        harness.wait_for_subscribers(publishers[topic], count, timeout_s=20.0)
    unpaced: list[int] = []
    with BagSource(BAG) as bag:
        for message in bag.messages(list(publishers)):
            publishers[message.topic].publish(message.data)
            if message.topic != IMAGE_TOPIC:
                continue
            stamp_ns = message.timestamp_ns
            try:
                wait_until(
                    lambda stamp_ns=stamp_ns: (slam.sync.last_ns or 0) >= stamp_ns,
                    timeout_s=PACE_TIMEOUT_S,
                    what=f'monoslam to process the image stamped {stamp_ns} ns',
                )
            except TimeoutError:
                unpaced.append(stamp_ns)
    return unpaced


def centre(message: Any) -> np.ndarray:
    p = message.pose.pose.position
    return np.array([p.x, p.y, p.z])


def test_the_pose_follows_the_ground_truth(pipeline: PipelineRun, truth: Truth) -> None:
    errors = [
        float(np.linalg.norm(centre(m) - truth.centres[stamp_to_ns(m.header.stamp)]))
        for m in pipeline.poses
    ]
    assert len(errors) >= MIN_POSES, f'images monoslam never processed: {pipeline.unpaced}'
    assert max(errors[:START_FRAMES]) < MAX_START_ERROR_M
    assert np.median(errors) < MAX_MEDIAN_ERROR_M and max(errors) < MAX_ERROR_M
    assert all(m.header.frame_id == 'monoslam_map' for m in pipeline.poses)
    for message in pipeline.poses:
        covariance = np.reshape(message.pose.covariance, (6, 6))
        assert np.allclose(covariance, covariance.T) and np.all(np.diag(covariance) > 0)


Pixels = dict[int, dict[int, tuple[float, float]]]


def labelled(messages: Iterable[Any], pixels: Pixels, truth: Truth) -> Counter[tuple[int, str]]:
    """Count the sightings in ShadowTrackArray (or FeatureTrackArray: status -1) messages by
    (status, what the label image shows under the feature's pixel in that image: 'static',
    'object' or 'nothing'); ``pixels``: image stamp -> track id -> (u, v)."""
    counts: Counter[tuple[int, str]] = Counter()
    for message in messages:
        stamp_ns = stamp_to_ns(message.header.stamp)
        in_image = pixels.get(stamp_ns, {})
        for track in message.tracks:
            if track.id not in in_image:
                continue
            u, v = in_image[track.id]
            label = int(truth.labels[stamp_ns][round(v), round(u)])
            kind = 'object' if label >= FIRST_OBJECT_LABEL else 'static' if label else 'nothing'
            counts[getattr(track, 'status', -1), kind] += 1
    return counts


def test_shadow_statuses_match_the_labels(pipeline: PipelineRun, truth: Truth) -> None:
    pixels = {
        stamp_to_ns(m.header.stamp): {t.id: (t.u, t.v) for t in m.tracks}
        for m in pipeline.features
    }
    handed = labelled(pipeline.handovers, pixels, truth)
    held = labelled(pipeline.tracks, pixels, truth)
    seen = labelled(pipeline.features, pixels, truth)
    static, dynamic, pending = ShadowTrack.STATIC, ShadowTrack.DYNAMIC, ShadowTrack.PENDING
    handed_total = sum(handed.values())
    dynamic_total = held[dynamic, 'static'] + held[dynamic, 'object']
    base_share = seen[-1, 'object'] / sum(seen.values())
    assert handed_total > MIN_HANDOVERS
    assert handed[static, 'static'] / handed_total >= MIN_STATIC_SHARE
    on_objects = held[dynamic, 'object'] + held[pending, 'object']
    assert held[dynamic, 'object'] / on_objects >= MIN_OBJECT_RECALL
    assert held[dynamic, 'object'] / dynamic_total >= MIN_DYNAMIC_ENRICHMENT * base_share


def test_the_shadow_filter_engages_and_fills_the_map(pipeline: PipelineRun, truth: Truth) -> None:
    """Issue 20's live figures: the Shadow filter processes at least 95 % of the images
    (shadow/tracks comes once per processed frame), hands over at least 100 features, and
    SLAM's map holds them, with the undecided features that filled it (fill_undecided) marked
    as not handed over (measured: 299 of 300 frames, 387 features, 137 map points before
    filling; 61 points, 5 of them handed over, with it: handovers enter only while fewer
    than target_measured features are measured)."""
    images = len(truth.centres)
    assert len(pipeline.tracks) >= MIN_SHADOW_SHARE * images
    handed = {track.id for message in pipeline.handovers for track in message.tracks}
    assert len(handed) >= MIN_HANDED_FEATURES
    points = np.frombuffer(bytes(pipeline.maps[-1].data), dtype=POINT_DTYPE)
    from_handover = points['handover'] == 1
    assert len(points) >= MIN_HANDED_FEATURES // 2
    assert set(points['id'][from_handover].astype(int)) <= handed
    assert np.count_nonzero(from_handover) >= 1


def test_the_poses_reach_the_shadow_filter_with_their_links(pipeline: PipelineRun) -> None:
    """monoslam publishes each pose's error covariances with its earlier poses' on
    monoslam/pose/link just before the pose; the shadow_filter attaches them (pose_links). All
    but the first pose after a start come with one (a link may come late: then that pose is
    taken as independent, counted)."""
    linked, unlinked = pipeline.links
    assert linked >= 0.9 * (linked + unlinked), pipeline.links


def test_map_path_and_tf_are_published_without_nan(pipeline: PipelineRun) -> None:
    assert pipeline.maps and pipeline.paths and pipeline.transforms
    cloud = pipeline.maps[-1]
    points = np.frombuffer(bytes(cloud.data), dtype=POINT_DTYPE)
    assert cloud.header.frame_id == 'monoslam_map' and len(points) == cloud.width > 10
    assert [f.name for f in cloud.fields] == list(POINT_DTYPE.names or ())
    assert np.any(points['handover'] == 1) and np.any(points['active'] == 1)
    path = pipeline.paths[-1]
    assert path.poses[-1].header.stamp == pipeline.poses[-1].header.stamp
    transform = pipeline.transforms[-1].transforms[0]
    # under MonoSLAM's own names: the camera's optical frame keeps its parent (REP 105)
    frames = (transform.header.frame_id, transform.child_frame_id)
    assert frames == ('monoslam_map', 'monoslam_camera')
    assert_finite(numbers(pipeline.poses) + numbers(pipeline.transforms) + numbers(pipeline.paths))
    for cloud in pipeline.maps:
        points = np.frombuffer(bytes(cloud.data), dtype=POINT_DTYPE)
        assert all(np.all(np.isfinite(points[name])) for name in ('x', 'y', 'z', 'sigma_m'))


def numbers(messages: Iterable[Any]) -> list[float]:
    """Every float of PoseWithCovarianceStamped, Path, TFMessage and FeatureTrackArray
    messages."""
    values: list[float] = []
    for message in messages:
        poses = [p.pose for p in getattr(message, 'poses', [])]
        if hasattr(message, 'pose'):
            poses.append(message.pose.pose)
            values += list(message.pose.covariance)
        for pose in poses:
            p, q = pose.position, pose.orientation
            values += [p.x, p.y, p.z, q.x, q.y, q.z, q.w]
        for transform in getattr(message, 'transforms', []):
            t, q = transform.transform.translation, transform.transform.rotation
            values += [t.x, t.y, t.z, q.x, q.y, q.z, q.w]
        values += [c for t in getattr(message, 'tracks', []) for c in (t.u, t.v)]
    return [float(v) for v in values]


def assert_finite(values: list[float]) -> None:
    assert values and all(math.isfinite(v) for v in values)


# --- bad input to a node process -----------------------------------------------------------


@pytest.fixture(scope='module')
def scene() -> DynamicSceneRun:
    return simulate_dynamic_scene(0, DynamicSceneConfig(duration_s=3.0))


def camera_info(run: DynamicSceneRun, fx_px: float | None = None, stamp_ns: int = 0) -> CameraInfo:
    fields = run.camera.camera_info()
    k = fields.k.copy()
    if fx_px is not None:
        k[0] = fx_px
    info = CameraInfo(width=fields.width, height=fields.height)
    info.header.frame_id = 'camera_optical_frame'
    ns_to_stamp(stamp_ns, info.header.stamp)
    info.distortion_model = fields.distortion_model
    info.d, info.k = fields.d.tolist(), k.tolist()
    info.r, info.p = fields.r.tolist(), fields.p.tolist()
    return info


class Inputs:
    """Publishes a scene frame's features and fiducials (true target corners) to the node."""

    def __init__(self, harness: RosHarness, run: DynamicSceneRun) -> None:
        self.run = run
        self.info = harness.publisher('camera/camera_info', CameraInfo)
        self.features = harness.publisher('features', FeatureTrackArray)
        self.fiducials = harness.publisher('fiducials', FiducialArray)
        self.handovers = harness.publisher('shadow/static_features', ShadowTrackArray)
        for publisher in (self.info, self.features, self.fiducials, self.handovers):
            harness.wait_for_subscribers(publisher)

    def send(
        self,
        index: int,
        *,
        stamp_ns: int | None = None,
        features: bool = True,
        target: bool = True,
        fiducials: bool = True,
        nan_id: int | None = None,
    ) -> int:
        frame = self.run.frames[index]
        stamp_ns = frame.stamp_ns if stamp_ns is None else stamp_ns
        message = FeatureTrackArray()
        ns_to_stamp(stamp_ns, message.header.stamp)
        message.header.frame_id = 'camera_optical_frame'
        if features:
            message.tracks = [
                FeatureTrack(id=int(i), u=math.nan if i == nan_id else float(u), v=float(v))
                for i, (u, v) in zip(frame.track_ids, frame.pixels, strict=True)
            ]
        self.features.publish(message)
        if fiducials:
            self.fiducials.publish(self.target(stamp_ns, index if target else None))
        return stamp_ns

    def target(self, stamp_ns: int, index: int | None) -> FiducialArray:
        message = FiducialArray()
        ns_to_stamp(stamp_ns, message.header.stamp)
        message.header.frame_id = 'camera_optical_frame'
        if index is None:
            return message
        frame = self.run.frames[index]
        pixels = target_pixels(InitTarget(), self.run.camera, frame.camera_rotation,
                               frame.camera_position)  # fmt: skip
        assert pixels is not None
        detection = FiducialDetection(id=0, dictionary='DICT_APRILTAG_36h11')
        detection.corners_px = [float(v) for v in pixels.ravel()]
        message.detections = [detection]
        return message

    def handover(self, track_id: int, position: Iterable[float], **changes: Any) -> None:
        message = ShadowTrackArray()
        message.header.frame_id = changes.pop('frame_id', 'monoslam_map')
        track = ShadowTrack(id=track_id, status=changes.pop('status', ShadowTrack.STATIC))
        track.position.x, track.position.y, track.position.z = (float(v) for v in position)
        track.position_covariance = (1e-4 * np.eye(3)).ravel().tolist()
        message.tracks = [track]
        self.handovers.publish(message)


def start_node(harness: RosHarness, *arguments: str) -> NodeProcess:
    command = [sys.executable, '-m', MODULE, '--ros-args', '--params-file', str(TARGET_CONFIG)]
    for argument in arguments:
        command += ['-p', argument]
    return harness.start_process('monoslam', command, env=tool_env())


def test_bad_inputs_are_logged_and_the_node_keeps_working(
    ros_harness: RosHarness, scene: DynamicSceneRun, tmp_path: Path
) -> None:
    trajectory = tmp_path / 'out' / 'trajectory.tum'
    node = start_node(
        ros_harness,
        'sync_horizon_s:=0.2',
        'publish_predictions:=true',
        'fill_undecided:=false',  # only the handovers below enter the map
        f'trajectory_file:={trajectory}',
    )
    poses = ros_harness.collect('monoslam/pose', PoseWithCovarianceStamped)
    predictions = ros_harness.collect('features/predicted', FeatureTrackArray)
    maps = ros_harness.collect('monoslam/map', PointCloud2, latched_qos())
    inputs = Inputs(ros_harness, scene)
    frames = scene.frames

    # features before any camera_info: held until it comes (it is best effort: repeat it)
    inputs.send(0, target=False)
    node.wait_for_line(LOG_TIMEOUT_S, 'no camera/camera_info received yet', 'holding 1')
    for _ in range(50):
        inputs.info.publish(camera_info(scene))
        if 'camera: 640x480' in node.log():
            break
        wait_until(lambda: 'camera: 640x480' in node.log(), timeout_s=0.2, what='camera')
    node.wait_for_line(LOG_TIMEOUT_S, 'camera: 640x480')

    # no target in view: waiting, and saying so
    inputs.send(1, target=False)
    node.wait_for_line(
        LOG_TIMEOUT_S, 'no initialization target (id 0 (DICT_APRILTAG_36h11, 0.6 m)', 'waiting'
    )
    assert len(poses) == 0

    # the target: started; then NaN pixels, out-of-order stamps, bad handovers
    started_ns = inputs.send(2)
    pose = poses.wait_for(lambda m: stamp_to_ns(m.header.stamp) == started_ns)
    assert np.linalg.norm(centre(pose) - frames[2].camera_position) < 0.1
    node.wait_for_line(LOG_TIMEOUT_S, f'started at stamp {started_ns} ns', 'camera at (')
    nan_id = int(frames[3].track_ids[0])
    inputs.send(3, nan_id=nan_id)
    node.wait_for_line(LOG_TIMEOUT_S, 'ignored features with non-finite pixels', f'ids {nan_id}')
    late_ns = inputs.send(1)
    node.wait_for_line(
        LOG_TIMEOUT_S, f'features frame at stamp {late_ns} ns dropped: not after the frame'
    )
    good_id = next(
        int(i) for i in frames[4].track_ids if not scene.point_moving[scene.track_point[int(i)]]
    )
    inputs.handover(good_id, scene.point_positions[4, scene.track_point[good_id]])
    inputs.handover(77, [math.nan, 0.0, 1.0])
    node.wait_for_line(
        LOG_TIMEOUT_S, 'handover of feature 77: position [nan, 0.0, 1.0] not finite; refused'
    )
    inputs.handover(78, [1.0, 2.0, 1.0], status=ShadowTrack.DYNAMIC)
    node.wait_for_line(LOG_TIMEOUT_S, 'handover of feature 78: status 2, not STATIC; refused')
    inputs.handover(79, [1.0, 2.0, 1.0], frame_id='odom')
    node.wait_for_line(
        LOG_TIMEOUT_S, "handover of feature 79: in frame 'odom', not map_frame 'monoslam_map'"
    )

    # predictions for the next image, triggered by its camera_info: the handed-over feature
    for index in range(4, 8):
        inputs.send(index)
    poses.wait_for(lambda m: stamp_to_ns(m.header.stamp) == frames[7].stamp_ns)
    inputs.info.publish(camera_info(scene, stamp_ns=frames[8].stamp_ns))
    predicted = predictions.wait_for(lambda m: stamp_to_ns(m.header.stamp) == frames[8].stamp_ns)
    assert [t.id for t in predicted.tracks] == [good_id]
    su, suv, sv = predicted.tracks[0].covariance  # its search region, px^2
    assert su > 0.0 and sv > 0.0 and su * sv > suv**2 and max(su, sv) < 1e4

    # an unusable camera_info is refused; a changed one is applied
    broken = camera_info(scene)
    broken.k = [0.0] * 9
    inputs.info.publish(broken)
    node.wait_for_line(
        LOG_TIMEOUT_S, 'camera/camera_info rejected', 'focal lengths', 'camera kept'
    )
    inputs.info.publish(camera_info(scene, fx_px=301.0))
    node.wait_for_line(LOG_TIMEOUT_S, 'camera/camera_info changed', 'fx=301')
    inputs.info.publish(camera_info(scene))

    # features whose fiducials do not come: processed alone once the horizon has passed
    alone_ns = inputs.send(8, fiducials=False)
    for index in range(9, 16):
        inputs.send(index)
    node.wait_for_line(
        LOG_TIMEOUT_S, f'features frame at stamp {alone_ns} ns processed without fiducials'
    )
    poses.wait_for(lambda m: stamp_to_ns(m.header.stamp) == alone_ns)

    # everything lost for lost_after_frames (15): tracking lost; the target: re-initialized
    for index in range(16, 40):
        inputs.send(index, features=False, target=False)
    node.wait_for_line(
        LOG_TIMEOUT_S, 'tracking lost: no feature or known point measured for 15 frames'
    )
    node.wait_for_line(LOG_TIMEOUT_S, 're-initializing from the target')
    again_ns = inputs.send(40)
    node.wait_for_line(LOG_TIMEOUT_S, f're-initialized at stamp {again_ns} ns')
    poses.wait_for(lambda m: stamp_to_ns(m.header.stamp) == again_ns)
    maps.wait_for_count(1)

    assert node.process.poll() is None
    node.process.send_signal(signal.SIGINT)
    assert node.process.wait(timeout=LOG_TIMEOUT_S) == 0
    assert 'Traceback' not in node.log()
    lines = trajectory.read_text().splitlines()
    assert len(lines) == len(poses.messages)
    assert all(len(line.split()) == 8 for line in lines)
    assert_finite([float(v) for line in lines for v in line.split()])
    assert_finite(numbers(poses.messages) + numbers(predictions.messages))


@pytest.mark.parametrize(
    ('parameter', 'value'),
    [
        ('initialize', 'sometimes'),
        ('target_size_m', '0.0'),
        ('target_xyz_m', '[1.0, 2.0]'),
        ('target_dictionary', 'DICT_QR'),
        ('gate_probability', '1.0'),
    ],
)
def test_invalid_parameter_is_named(parameter: str, value: str) -> None:
    error = invalid_parameter_error([sys.executable, '-m', MODULE], parameter, value)
    assert f'parameter monoslam.{parameter}=' in error
    assert error.startswith('monoslam: error: ')
