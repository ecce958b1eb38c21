"""The feature_tracker node without DDS: its parameter contract (docstring, YAML, core
config), the processor's rules (stamp order, camera_info, predictions), the message filling
and the launch file."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from monoslam_shadow_node.common.notices import Notice
from monoslam_shadow_node.feature_tracker import node as feature_tracker_node
from monoslam_shadow_node.feature_tracker import settings
from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig
from monoslam_shadow_node.feature_tracker.node import KindThrottle
from monoslam_shadow_node.feature_tracker.processor import (
    FeatureFrame,
    FeatureTrackingProcessor,
    Outcome,
    feature_frame_cdr,
    status_line,
)
from slam_core.errors import ParameterError
from slam_interfaces.msg import FeatureTrack, FeatureTrackArray
from slam_ros.testing.launch_files import check_launched_node, launched_node

PACKAGE_DIR = Path(__file__).resolve().parents[1]
CONFIG = PACKAGE_DIR / 'config' / 'feature_tracker.yaml'
LAUNCH = PACKAGE_DIR / 'launch' / 'feature_tracker.launch.py'
MS = 1_000_000
S = 1_000_000_000


# --- parameters ----------------------------------------------------------------------------


def test_config_yaml_holds_the_defaults_and_they_are_the_core_defaults() -> None:
    values = settings.PARAMETERS.read_yaml(CONFIG)
    assert values == settings.PARAMETERS.defaults()
    assert settings.tracker_config(values) == TrackerConfig()
    node = settings.node_settings(values)
    assert node.image_transport == 'raw' and not node.use_predictions
    assert node.prediction_timeout_s == 0.1 and node.restart_backstep_ns == S


def test_every_core_setting_has_a_parameter_with_a_unit_where_it_has_one() -> None:
    fields = {field.name for field in dataclasses.fields(TrackerConfig)}
    assert {s.field for s in settings.CORE_PARAMETERS} == fields
    for setting in settings.PARAMETERS:
        unit = ' px' in setting.description or ', s ' in setting.description
        assert not unit or setting.name.endswith(('_px', '_s')), setting.name


def test_parameters_reach_the_core_config() -> None:
    values = {
        **settings.PARAMETERS.defaults(),
        'max_features': 300,
        'detector': 'fast',
        'fb_threshold_px': 0.5,
        'min_distance_px': 7,
    }
    config = settings.tracker_config(values)
    assert config.max_features == 300 and config.detector == 'fast'
    assert config.fb_threshold_px == 0.5 and config.min_distance_px == 7.0


@pytest.mark.parametrize(
    ('name', 'value', 'message'),
    [
        ('max_features', 0, r'parameter feature_tracker\.max_features=0: must be >= 1'),
        ('max_features', 1.5, r'parameter feature_tracker\.max_features=1\.5: must be an integer'),
        (
            'detector',
            'orb',
            r"parameter feature_tracker\.detector='orb': must be one of 'shi_tomasi', 'fast'",
        ),
        (
            'quality_level',
            0.0,
            r'parameter feature_tracker\.quality_level=0\.0: must be in \(0, 1\)',
        ),
        (
            'min_distance_px',
            0.5,
            r'parameter feature_tracker\.min_distance_px=0\.5: must be >= 1',
        ),
        (
            'fb_threshold_px',
            math.nan,
            r'parameter feature_tracker\.fb_threshold_px=nan: must be a finite',
        ),
        (
            'lk_pyramid_levels',
            9,
            r'parameter feature_tracker\.lk_pyramid_levels=9: must be in \[0, 8\]',
        ),
        (
            'subpixel_refinement',
            1,
            r'parameter feature_tracker\.subpixel_refinement=1: must be true or false',
        ),
        ('grid_rows', 'four', r"parameter feature_tracker\.grid_rows='four': must be an integer"),
        (
            'reid_max_alignments',
            -1,
            r'parameter feature_tracker\.reid_max_alignments=-1: must be >= 0',
        ),
    ],
)
def test_invalid_tracker_parameters_are_named(name: str, value: object, message: str) -> None:
    with pytest.raises(ParameterError, match=message):
        settings.tracker_config({**settings.PARAMETERS.defaults(), name: value})


@pytest.mark.parametrize(
    ('name', 'value', 'message'),
    [
        (
            'image_transport',
            'theora',
            r"parameter feature_tracker\.image_transport='theora': must be one of",
        ),
        (
            'prediction_timeout_s',
            -0.1,
            r'parameter feature_tracker\.prediction_timeout_s=-0\.1: must be >= 0',
        ),
        (
            'restart_backstep_s',
            0.0,
            r'parameter feature_tracker\.restart_backstep_s=0\.0: must be > 0',
        ),
        (
            'use_predictions',
            'yes',
            r"parameter feature_tracker\.use_predictions='yes': must be true or false",
        ),
    ],
)
def test_invalid_node_parameters_are_named(name: str, value: object, message: str) -> None:
    with pytest.raises(ParameterError, match=message):
        settings.node_settings({**settings.PARAMETERS.defaults(), name: value})


def test_a_missing_parameter_is_named() -> None:
    values = settings.PARAMETERS.defaults()
    del values['max_features']
    with pytest.raises(
        ParameterError, match=r'parameter feature_tracker\.max_features is missing'
    ):
        settings.tracker_config(values)


# --- processor -----------------------------------------------------------------------------


def textured(seed: int = 0, width: int = 320, height: int = 240) -> np.ndarray:
    noise = np.random.default_rng(seed).uniform(0.0, 255.0, (height, width)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 2.0) * 3.0 - 255.0, 0, 255).astype(np.uint8)


SCENE = textured(width=360, height=280)


def shifted(du: int, dv: int) -> np.ndarray:
    """The 320x240 view of SCENE moved by (du, dv) px (0 <= du, dv <= 20)."""
    return SCENE[20 - dv : 260 - dv, 20 - du : 340 - du].copy()


IMAGE = shifted(0, 0)


def frames(outcomes: list[Outcome]) -> list[FeatureFrame]:
    return [o for o in outcomes if isinstance(o, FeatureFrame)]


def notices(outcomes: list[Outcome]) -> list[Notice]:
    return [o for o in outcomes if isinstance(o, Notice)]


def camera(processor: FeatureTrackingProcessor, **changes: Any) -> Notice | None:
    fields: dict[str, Any] = {
        'frame_id': 'camera_optical_frame',
        'width': 320,
        'height': 240,
        'k': [300.0, 0.0, 160.0, 0.0, 300.0, 120.0, 0.0, 0.0, 1.0],
        'd': [0.0] * 5,
        'distortion_model': 'plumb_bob',
        **changes,
    }
    return processor.set_camera_info(**fields)


def processor(**options: Any) -> FeatureTrackingProcessor:
    return FeatureTrackingProcessor(TrackerConfig(max_features=40), **options)


def test_images_are_tracked_without_camera_info_and_that_is_said_once() -> None:
    tracker = processor()
    first = tracker.add_image(1 * S, 'cam', IMAGE, now_s=0.0)
    (notice,) = notices(first)
    assert notice.kind == 'no_camera_info' and 'camera/camera_info' in notice.text
    (frame,) = frames(first)
    assert frame.stamp_ns == S and frame.frame_id == 'cam' and len(frame.features.ids) == 40
    second = tracker.add_image(2 * S, 'cam', shifted(1, 1), now_s=0.0)
    counts = frames(second)[0].features.counts
    assert notices(second) == [] and counts.tracked + counts.border == 40 and counts.tracked


def test_camera_info_checks_the_size_names_the_frame_and_restarts_on_change() -> None:
    tracker = processor()
    notice = camera(tracker)
    assert notice is not None and notice.kind == 'camera' and '320x240 px' in notice.text
    assert camera(tracker) is None  # the same camera again: nothing to say
    (frame,) = frames(tracker.add_image(1 * S, '', IMAGE, now_s=0.0))
    assert frame.frame_id == 'camera_optical_frame'  # the image had none
    (drop,) = tracker.add_image(2 * S, 'cam', textured(width=640, height=480), now_s=0.0)
    assert isinstance(drop, Notice) and drop.kind == 'size_mismatch'
    assert drop.text == (
        f'image at stamp {2 * S} ns dropped: it is 640x480 px but camera/camera_info says '
        '320x240 px'
    )
    ids = set(frame.features.ids.tolist())
    changed = camera(tracker, k=[310.0, 0.0, 160.0, 0.0, 310.0, 120.0, 0.0, 0.0, 1.0])
    assert changed is not None and changed.kind == 'camera_changed'
    assert 'fx=310' in changed.text and '40 tracks dropped' in changed.text
    (after,) = frames(tracker.add_image(3 * S, 'cam', shifted(1, 0), now_s=0.0))
    assert after.features.counts.reset == 40 and after.features.counts.tracked == 0
    assert min(after.features.ids) > max(ids)  # ids go on
    assert tracker.stats.restarts == 1 and tracker.stats.images_dropped == {'size_mismatch': 1}


@pytest.mark.parametrize(
    ('changes', 'problem'),
    [
        ({'width': 0}, 'camera_info width=0: must be an integer > 0'),
        ({'k': [math.nan] * 9}, 'must be 9 finite numbers'),
        ({'k': [1.0] * 4}, 'camera_info k has 4 values; expected 9'),
        # fx = 0 was once taken and every track dropped.
        ({'k': [0.0, 0.0, 160.0, 0.0, 300.0, 120.0, 0.0, 0.0, 1.0]}, 'fx=0, fy=300'),
        ({'d': [0.0, math.inf, 0.0, 0.0, 0.0]}, 'plumb_bob needs 5 finite coefficients'),
        ({'distortion_model': 'fisheye'}, "distortion_model='fisheye': not supported"),
    ],
)
def test_an_unusable_camera_info_is_refused(changes: dict[str, Any], problem: str) -> None:
    tracker = processor()
    notice = camera(tracker, **changes)
    assert notice is not None and notice.kind == 'camera_rejected' and problem in notice.text
    assert tracker.camera is None
    camera(tracker)
    again = camera(tracker, **changes)
    assert again is not None and 'previous camera kept' in again.text
    assert tracker.camera is not None and tracker.camera.width == 320
    assert tracker.stats.camera_rejected == 2


def test_out_of_order_and_repeated_stamps_drop_the_image_naming_both() -> None:
    tracker = processor()
    tracker.add_image(10 * S, 'cam', IMAGE, now_s=0.0)
    (older,) = tracker.add_image(10 * S - 33 * MS, 'cam', shifted(1, 0), now_s=0.0)
    assert isinstance(older, Notice) and older.kind == 'out_of_order'
    assert older.text == (
        f'image at stamp {10 * S - 33 * MS} ns dropped: it is older than the image before it '
        f'({10 * S} ns); images must come in stamp order'
    )
    (same,) = tracker.add_image(10 * S, 'cam', shifted(1, 0), now_s=0.0)
    assert isinstance(same, Notice) and same.kind == 'repeated_stamp'
    assert 'has the same stamp as the image before it' in same.text
    (frame,) = frames(tracker.add_image(10 * S + 33 * MS, 'cam', shifted(1, 0), now_s=0.0))
    counts = frame.features.counts  # the drops did not disturb the tracks:
    assert counts.tracked + counts.border == 40 and counts.dropped == counts.border
    assert tracker.stats.images_dropped == {'out_of_order': 1, 'repeated_stamp': 1}


def test_a_big_step_back_restarts_tracking_with_new_ids() -> None:
    tracker = processor(restart_backstep_ns=S)
    (first,) = frames(tracker.add_image(100 * S, 'cam', IMAGE, now_s=0.0))
    outcomes = tracker.add_image(5 * S, 'cam', IMAGE, now_s=0.0)
    (restart,) = notices(outcomes)
    assert restart.kind == 'restart' and f'from {100 * S} ns to {5 * S} ns' in restart.text
    (frame,) = frames(outcomes)
    assert frame.features.counts.reset == 40 and frame.features.ids.min() == 41
    assert first.features.ids.max() == 40


def test_an_image_size_change_without_camera_info_restarts() -> None:
    tracker = processor()
    tracker.add_image(1 * S, 'cam', IMAGE, now_s=0.0)
    outcomes = tracker.add_image(2 * S, 'cam', textured(width=160, height=120), now_s=0.0)
    (frame,) = frames(outcomes)
    assert frame.features.counts.reset == 40
    assert [n.kind for n in notices(outcomes)] == ['image_size_changed']


def test_images_the_tracker_cannot_use_are_dropped() -> None:
    tracker = processor()
    (drop,) = notices(tracker.add_image(1 * S, 'cam', np.zeros((0, 0), np.uint8), now_s=0.0))[1:]
    assert drop.kind == 'bad_image' and 'empty image' in drop.text
    (frame,) = frames(tracker.add_image(1 * S, 'cam', IMAGE, now_s=0.0))  # stamp not taken
    assert len(frame.features.ids) == 40


def test_predictions_given_first_are_used_without_waiting() -> None:
    tracker = processor(use_predictions=True, prediction_timeout_s=1.0)
    assert frames(tracker.add_image(1 * S, 'cam', IMAGE, now_s=0.0)) == []  # waits
    (first,) = frames(tracker.flush())
    ids, pixels = first.features.ids, first.features.pixels + np.array([5.0, 3.0])
    assert tracker.add_predictions(2 * S, ids, pixels) == []
    (frame,) = frames(tracker.add_image(2 * S, 'cam', shifted(5, 3), now_s=0.0))
    assert frame.predicted and frame.features.counts.predicted == frame.features.counts.tracked
    assert tracker.stats.predictions_used == 1


def test_an_image_waits_for_its_prediction_until_the_timeout() -> None:
    tracker = processor(use_predictions=True, prediction_timeout_s=0.05)
    assert frames(tracker.add_image(1 * S, 'cam', IMAGE, now_s=10.0)) == []
    assert tracker.waiting and tracker.poll(now_s=10.04) == []
    (first,) = frames(tracker.poll(now_s=10.05))  # overdue: tracked without
    assert not first.predicted and not tracker.waiting
    # the prediction comes after its image: the image is tracked as soon as it comes
    assert tracker.add_image(2 * S, 'cam', shifted(4, 0), now_s=11.0) == []
    ids, pixels = first.features.ids, first.features.pixels + np.array([4.0, 0.0])
    (second,) = frames(tracker.add_predictions(2 * S, ids, pixels))
    assert second.stamp_ns == 2 * S and second.predicted
    # late (image tracked already) and skipped predictions
    assert tracker.add_predictions(2 * S, ids, pixels) == []
    assert tracker.add_image(3 * S, 'cam', shifted(8, 0), now_s=12.0) == []
    (third,) = frames(tracker.add_predictions(4 * S, ids, pixels))  # for a later image
    assert third.stamp_ns == 3 * S and not third.predicted
    (fourth,) = frames(tracker.add_image(4 * S, 'cam', shifted(8, 0), now_s=13.0))
    assert fourth.predicted  # the prediction for 4 s came first
    stats = tracker.stats
    assert (stats.predictions_used, stats.predictions_missed, stats.predictions_late) == (2, 2, 1)


def test_the_next_image_releases_the_waiting_one() -> None:
    tracker = processor(use_predictions=True, prediction_timeout_s=10.0)
    tracker.add_image(1 * S, 'cam', IMAGE, now_s=0.0)
    released = frames(tracker.add_image(2 * S, 'cam', shifted(1, 0), now_s=0.1))
    assert [f.stamp_ns for f in released] == [1 * S]
    assert [f.stamp_ns for f in frames(tracker.flush())] == [2 * S]


def test_predictions_are_ignored_unless_asked_for() -> None:
    tracker = processor()
    assert tracker.add_predictions(2 * S, np.array([1]), np.array([[1.0, 2.0]])) == []
    (frame,) = frames(tracker.add_image(2 * S, 'cam', IMAGE, now_s=0.0))
    assert not frame.predicted and tracker.stats.predictions_missed == 0


def test_status_line_counts_frames_tracks_and_drops() -> None:
    tracker = processor()
    tracker.add_image(1 * S, 'cam', IMAGE, now_s=0.0)
    tracker.add_image(S // 2, 'cam', IMAGE, now_s=0.0)
    tracker.add_image(2 * S, 'cam', shifted(2, 1), now_s=0.0)
    line = status_line(tracker.stats, 29.5)
    stats = tracker.stats
    assert line.startswith('2 images tracked (29.5/s), ')
    assert f'{stats.latest_features} features in the latest' in line
    assert f'{stats.started} tracks started' in line and stats.started >= 40
    assert 'images dropped: out of order 1' in line and 'predictions' not in line


def test_throttle_lets_one_line_per_kind_through_and_counts_the_rest() -> None:
    throttle = KindThrottle(2.0)
    assert throttle.admit('out_of_order', 0.0) == 0
    assert throttle.admit('out_of_order', 1.0) is None
    assert throttle.admit('size_mismatch', 1.0) == 0  # another kind is not held back
    assert throttle.admit('out_of_order', 1.5) is None
    assert throttle.admit('out_of_order', 2.0) == 2


# --- conversions ---------------------------------------------------------------------------


def test_feature_frames_are_serialized_as_rclpy_serializes_the_message() -> None:
    tracker = processor()
    (frame,) = frames(tracker.add_image(3 * S + 5, 'camera_optical_frame', IMAGE, now_s=0.0))
    data = feature_frame_cdr(frame)
    message = FeatureTrackArray()
    message.header.stamp.sec, message.header.stamp.nanosec = 3, 5
    message.header.frame_id = 'camera_optical_frame'
    ids, pixels = frame.features.ids.tolist(), frame.features.pixels.tolist()
    message.tracks = [FeatureTrack(id=i, u=u, v=v) for i, (u, v) in zip(ids, pixels, strict=True)]
    assert len(data) == len(serialize_message(message))  # padding bytes are not defined
    read = deserialize_message(data, FeatureTrackArray)
    assert (read.header.stamp.sec, read.header.stamp.nanosec) == (3, 5)
    assert read.header.frame_id == 'camera_optical_frame'
    assert [(t.id, t.u, t.v) for t in read.tracks] == [(t.id, t.u, t.v) for t in message.tracks]
    assert all(not any(t.covariance) and not any(t.warp) for t in read.tracks)
    # a non-finite pixel (which the core never returns) is left out
    broken_pixels = frame.features.pixels.copy()
    broken_pixels[0, 1] = math.nan
    broken = dataclasses.replace(frame.features, pixels=broken_pixels)
    read = deserialize_message(
        feature_frame_cdr(dataclasses.replace(frame, features=broken)), FeatureTrackArray
    )
    assert len(read.tracks) == 39 and all(math.isfinite(t.v) for t in read.tracks)
    assert [t.id for t in read.tracks] == ids[1:]


# --- launch file ---------------------------------------------------------------------------


def test_launch_file_starts_the_installed_executable_with_its_config(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """launch is not installed here: run the launch file against recording stand-ins."""
    launched = launched_node(LAUNCH, monkeypatch)
    check_launched_node(
        launched,
        package_dir=PACKAGE_DIR,
        entry_point='monoslam_shadow_node.feature_tracker.node:main',
        config=CONFIG,
    )
    node, arguments = launched.node, launched.arguments
    assert launched.remapped == {
        feature_tracker_node.IMAGE_TOPIC,
        feature_tracker_node.COMPRESSED_TOPIC,
        feature_tracker_node.CAMERA_INFO_TOPIC,
        feature_tracker_node.PREDICTIONS_TOPIC,
        feature_tracker_node.FEATURES_TOPIC,
    }
    for _, target in node.kwargs['remappings']:
        first = target[0] if isinstance(target, list) else target
        assert first.args[0] in arguments
    compressed = dict(node.kwargs['remappings'])[feature_tracker_node.COMPRESSED_TOPIC]
    assert compressed[0].args == ('image',) and compressed[1] == '/compressed'
