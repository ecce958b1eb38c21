"""The feature tracker's detection period (``detect_every_n_frames``, 3 by default): new
features start every third image and at once when no track is left; and the pyramid levels
its forward-backward pass climbs."""

from __future__ import annotations

import numpy as np
from test_feature_tracker_core import (
    HEIGHT,
    WIDTH,
    check_output,
    shifted,
    texture,
    to_gray,
    warped,
)

from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig
from monoslam_shadow_node.feature_tracker.core.feature_tracker import FeatureTracker


def test_detection_runs_every_third_image_by_default_and_whenever_no_track_is_left() -> None:
    """Between detections a lost track leaves its place empty; the third image after a
    detection fills it. An image with no track left detects at once."""
    scene = texture(HEIGHT, WIDTH, seed=0)
    tracker = FeatureTracker()
    assert tracker.config.detect_every_n_frames == 3
    news = []
    for k in range(7):
        image = warped(scene, shifted(1.0 * k, 0.5 * k))
        if k in (1, 4):  # an object passes over cell (1, 1): its tracks die
            image[120:240, 160:320] = to_gray(texture(120, 160, seed=5 + k))
        result = tracker.track(image)
        check_output(result, tracker.config)
        news.append(result.counts.new)
    assert news[0] == 150 and news[1] == news[2] == news[4] == news[5] == 0
    assert news[3] > 0 and news[6] > 0
    # nothing left (a blank image drops every track): the next image detects at once
    tracker.track(np.full((HEIGHT, WIDTH), 90, np.uint8))
    assert tracker.track(warped(scene, np.eye(3))).counts.new == 150


def test_the_backward_pass_climbs_the_levels_the_forward_correction_needs() -> None:
    """A shift within a quarter of the 21 px window per level: 5.25 px on the image, 10.5 px
    one level up, 21 px two up; never more levels than lk_pyramid_levels."""
    tracker = FeatureTracker(TrackerConfig(lk_window_px=21, lk_pyramid_levels=3))
    shifts = (0, 5, 6, 10, 11, 21, 22, 500)
    levels = [tracker._levels_for(np.array([0.1, shift])) for shift in shifts]
    assert levels == [0, 0, 1, 1, 2, 2, 3, 3]
    assert tracker._levels_for(np.zeros(0)) == 0  # no track left to check
    assert FeatureTracker(TrackerConfig(lk_pyramid_levels=1))._levels_for(np.array([500.0])) == 1
