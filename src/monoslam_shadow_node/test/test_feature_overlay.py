"""feature_tracker's debug image (feature_overlay): each feature in its latest status colour."""

from __future__ import annotations

import numpy as np
import pytest

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING, STATIC
from monoslam_shadow_node.feature_tracker.overlay import UNKNOWN, StatusBook, draw_features


def test_the_book_keeps_the_latest_status_of_the_ids_named_most_recently() -> None:
    book = StatusBook(capacity=3)
    assert book.update([(1, PENDING), (2, PENDING), (3, 7)]) == 2  # 7 is no status
    assert book.status(3) == UNKNOWN
    book.update([(1, STATIC)])
    book.update([(1, DYNAMIC)])  # revoked: SLAM found it moving
    assert book.status(1) == DYNAMIC
    book.update([(4, STATIC), (5, PENDING)])  # 2 was named longest ago
    assert len(book) == 3 and book.status(2) == UNKNOWN
    assert [book.status(i) for i in (1, 4, 5)] == [DYNAMIC, STATIC, PENDING]
    with pytest.raises(ValueError, match='capacity'):
        StatusBook(0)


def test_each_feature_is_drawn_in_its_status_colour() -> None:
    image = np.full((120, 160), 128, np.uint8)
    book = StatusBook()
    book.update([(10, STATIC), (11, DYNAMIC), (12, PENDING)])
    ids = np.array([10, 11, 12, 13])
    pixels = np.array([[30.0, 60.0], [70.0, 60.0], [110.0, 60.0], [140.0, 100.0]])
    canvas, counts = draw_features(image, ids, pixels, book)
    assert canvas.shape == (120, 160, 3) and canvas.dtype == np.uint8
    assert counts == {'unknown': 1, 'pending': 1, 'static': 1, 'dynamic': 1}
    b, g, r = (int(v) for v in canvas[60, 30])
    assert b > 200 and r < 60  # static: blue
    b, g, r = (int(v) for v in canvas[60, 70])
    assert g > 150 and b < 60 and r < 60  # dynamic: green
    b, g, r = (int(v) for v in canvas[60, 110])
    assert r > 200 and g < 60  # pending: red
    assert tuple(canvas[100, 140]) == (128, 128, 128)  # unknown: a hollow circle
    assert int(canvas[100, 144, 2]) > 180
    assert tuple(canvas[5, 150]) == (128, 128, 128)  # the image is otherwise kept
    assert (image == 128).all()  # and not drawn on
