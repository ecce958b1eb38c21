"""Box search (core.roi): the plan of whole-image and box searches, and the processor that
follows markers with it finds what whole-image searches find, at the same corners."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from marker_detector.core.detector_config import DetectorConfig
from marker_detector.core.frame_types import ExtrinsicsConfig
from marker_detector.core.rendering import MarkerPlacement, render_markers
from marker_detector.core.roi import SearchPlan, merge_boxes
from marker_detector.detector.processor import MarkerProcessor
from slam_core.camera import CameraModel
from slam_core.geometry.so3 import rotation_from_vector

CAMERA = CameraModel(
    640,
    480,
    np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]]),
    np.array([-0.28, 0.09, 0.0008, -0.0006, -0.01]),
    'plumb_bob',
)
FACING = np.diag([1.0, -1.0, -1.0])
SQUARE = np.array([[100.0, 100.0], [150.0, 100.0], [150.0, 150.0], [100.0, 150.0]])
SHAPE = (480, 640)


def test_period_one_searches_every_whole_image() -> None:
    plan = SearchPlan()
    for stamp in range(5):
        assert plan.boxes(stamp, SHAPE) is None
        plan.searched(True, {0: SQUARE})
    assert plan.followed == {}
    assert (plan.full_searches, plan.box_searches) == (5, 0)


def test_a_period_of_three_searches_the_whole_image_every_third_frame() -> None:
    plan = SearchPlan(period=3, margin_px=10.0)
    kinds = []
    for stamp in range(7):
        boxes = plan.boxes(stamp, SHAPE)
        kinds.append('whole' if boxes is None else 'box')
        plan.searched(boxes is None, {0: SQUARE})
    assert kinds == ['whole', 'box', 'box', 'whole', 'box', 'box', 'whole']
    # the box: the corners' bounds grown by the margin and a quarter of the 50 px extent
    plan.searched(True, {0: SQUARE})
    assert plan.boxes(8, SHAPE) == [(77, 77, 174, 174)]


def test_no_whole_image_search_while_every_wanted_id_is_followed() -> None:
    plan = SearchPlan(period=2, wanted=frozenset({0}))
    kinds = []
    for stamp, markers in enumerate([{0: SQUARE}] * 5 + [{}, {}, {0: SQUARE}, {0: SQUARE}]):
        boxes = plan.boxes(stamp, SHAPE)
        kinds.append('whole' if boxes is None else 'box')
        plan.searched(boxes is None, markers)  # frames 5, 6: the target is gone
    assert kinds == ['whole', 'box', 'box', 'box', 'box', 'box', 'whole', 'whole', 'box']
    # another wanted id not followed yet: the period holds
    plan = SearchPlan(period=2, wanted=frozenset({0, 7}))
    plan.searched(True, {0: SQUARE})
    assert plan.boxes(1, SHAPE) is not None
    plan.searched(False, {0: SQUARE})
    assert plan.boxes(2, SHAPE) is None


def test_nothing_followed_stamps_back_and_image_borders() -> None:
    plan = SearchPlan(period=4)
    assert plan.boxes(10, SHAPE) is None  # nothing followed yet
    plan.searched(True, {})
    assert plan.boxes(11, SHAPE) is None  # nothing found: search the whole image again
    plan.searched(True, {3: SQUARE - 90.0})  # near the top-left corner: the box is clipped
    boxes = plan.boxes(12, SHAPE)
    assert boxes is not None and boxes[0][:2] == (0, 0)
    plan.searched(False, {3: SQUARE - 90.0})
    assert plan.boxes(5, SHAPE) is None  # the stamps went back: a new run
    assert plan.followed == {}


def test_a_box_search_that_misses_a_followed_marker_asks_for_the_whole_image() -> None:
    plan = SearchPlan(period=5)
    plan.searched(True, {1: SQUARE, 2: SQUARE + 300.0})
    assert not plan.needs_full_search({1, 2, 7})
    assert plan.needs_full_search({1})


def test_overlapping_boxes_merge_until_none_overlap() -> None:
    assert merge_boxes([(0, 0, 10, 10), (5, 5, 20, 20), (30, 30, 40, 40)]) == [
        (0, 0, 20, 20),
        (30, 30, 40, 40),
    ]
    assert merge_boxes([(0, 0, 10, 10), (20, 0, 30, 10), (5, 0, 25, 10)]) == [(0, 0, 30, 10)]


@pytest.mark.parametrize(('period', 'margin'), [(0, 32.0), (2.5, 32.0), (3, -1.0), (3, np.nan)])
def test_bad_settings_are_refused(period: int, margin: float) -> None:
    with pytest.raises(ValueError, match='search'):
        SearchPlan(period=period, margin_px=margin)


def frames(rng: np.random.Generator) -> list[np.ndarray]:
    """A 0.16 m marker drifting across the view (about 13 px a frame, then a 180 px jump
    past the margin), and a second one coming into view halfway through."""
    images = []
    for k in range(12):
        x = -0.3 + 0.03 * k + (0.4 if k >= 9 else 0.0)
        placements = [
            MarkerPlacement(5, 0.16, rotation_from_vector(np.array([0.2, 0.05 * k, 0.0])) @ FACING,
                            np.array([x, 0.05, 1.2]))
        ]  # fmt: skip
        if k >= 6:
            placements.append(MarkerPlacement(9, 0.16, FACING, np.array([0.25, -0.2, 1.5])))
        image = cv2.GaussianBlur(render_markers(CAMERA, placements, 120.0), (0, 0), 0.7)
        image += rng.normal(0.0, 1.5, image.shape)
        images.append(np.clip(np.round(image), 0, 255).astype(np.uint8))
    return images


def test_followed_markers_are_found_at_the_whole_image_searchs_corners() -> None:
    images = frames(np.random.default_rng(4))
    outputs = {}
    for period in (1, 4):
        processor = MarkerProcessor(
            DetectorConfig(), ExtrinsicsConfig(source='parameters'), SearchPlan(period=period)
        )
        processor.set_camera_info('cam', 640, 480, CAMERA.K.ravel().tolist(),
                                  CAMERA.dist_coeffs.tolist(), 'plumb_bob')  # fmt: skip
        outputs[period] = [processor.process(k, 'cam', image) for k, image in enumerate(images)]
        plan = processor.search
    # 0 whole (nothing followed); 1, 2, 3 box; 4 whole (the period); 5, 6, 7 box (id 9,
    # in view from 6, waits); 8 whole; 9 the jump: a box miss, then the whole image; 10, 11 box
    assert (plan.full_searches, plan.box_searches) == (4, 8)
    found = {p: [sorted(d.id for d in out.detections) for out in outputs[p]] for p in outputs}
    assert found[1] == [[5]] * 6 + [[5, 9]] * 6
    assert found[4] == [[5]] * 8 + [[5, 9]] * 4  # id 9 at the next whole search
    for every, boxed in zip(outputs[1], outputs[4], strict=True):
        corners = {d.id: d.corners_px for d in every.detections}
        for detection in boxed.detections:
            np.testing.assert_allclose(detection.corners_px, corners[detection.id], atol=0.01)
