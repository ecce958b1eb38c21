"""feature_tracker: which dropped tracks it remembers for re-identification (``max_dormant``):
SLAM's map features, the ids of the latest predictions, are forgotten last."""

from __future__ import annotations

import numpy as np
from test_feature_tracker_core import (
    HEIGHT,
    WIDTH,
    check_output,
    moved,
    shifted,
    texture,
    warped,
)

from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig
from monoslam_shadow_node.feature_tracker.core.feature_tracker import FeatureTracker
from monoslam_shadow_node.feature_tracker.core.feature_types import Predictions, TrackedFeatures


def test_a_map_feature_is_remembered_longer_than_tracks_no_map_holds() -> None:
    """View A, then two unrelated views whose dropped tracks alone fill ``max_dormant``: A's
    tracks come back in view A when SLAM kept predicting them (its map's features, out of view
    meanwhile); without those predictions their templates were forgotten first."""
    source = texture(HEIGHT, WIDTH, seed=5)
    back = shifted(3.0, -2.0)

    # view A fills max_features, and each away view's drops alone fill max_dormant
    config = TrackerConfig(max_features=120, detect_every_n_frames=1, max_dormant=120)

    def run(predicted_away: bool) -> TrackedFeatures:
        tracker = FeatureTracker(config)
        first = tracker.track(warped(source, np.eye(3)))
        assert len(first.ids) == config.max_features
        outside = np.full((len(first.ids), 2), -50.0)  # predicted out of view: no search
        away = Predictions(first.ids, outside, np.zeros((len(first.ids), 2, 2)))
        for seed in (6, 7):
            seen = tracker.track(
                warped(texture(HEIGHT, WIDTH, seed=seed), np.eye(3)),
                away if predicted_away else None,
            )
            assert seen.counts.new >= 50 and seen.counts.revived == 0
        truth = moved(back, first.pixels)
        covariance = np.broadcast_to(16.0 * np.eye(2), (len(first.ids), 2, 2))
        result = tracker.track(warped(source, back), Predictions(first.ids, truth, covariance))
        check_output(result, config)
        return result

    kept = run(predicted_away=True)
    assert kept.counts.revived >= 0.8 * kept.counts.searched > 0
    forgotten = run(predicted_away=False)  # a few of A's tracks lasted into the first away
    assert forgotten.counts.searched <= 0.05 * kept.counts.searched
    assert forgotten.counts.revived <= 0.05 * kept.counts.revived
