"""classification_figure: statuses as of an image's stamp and the images nearest the asked
times (the tiling is tum_label_figure's; the bag reading is exercised on the graph's
recording by bench/monoslam_real_table.sh)."""

from __future__ import annotations

import pytest

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING, STATIC
from monoslam_shadow_node.feature_tracker.overlay import UNKNOWN
from slam_evaluation.classification_figure import (
    StatusEvent,
    nearest_stamps,
    statuses_as_of,
)


def test_a_status_counts_from_its_stamp_on_in_stamp_order() -> None:
    events = [
        StatusEvent(300, ((1, DYNAMIC),)),  # arrives first, stamped later
        StatusEvent(100, ((1, PENDING), (2, PENDING))),
        StatusEvent(200, ((2, STATIC),)),
    ]
    before = statuses_as_of(events, 150)
    assert before.status(1) == PENDING and before.status(2) == PENDING
    after = statuses_as_of(events, 300)
    assert after.status(1) == DYNAMIC and after.status(2) == STATIC
    assert statuses_as_of(events, 50).status(1) == UNKNOWN


def test_the_nearest_images_to_the_times_and_no_images_named() -> None:
    stamps = [10**18 + k * 33_333_333 for k in range(100)]
    assert nearest_stamps(stamps[::-1], [0.0, 1.0, 100.0]) == [stamps[0], stamps[30], stamps[-1]]
    with pytest.raises(ValueError, match='no images'):
        nearest_stamps([], [1.0])
