"""marker_board: a board of markers around the initialization target."""

from __future__ import annotations

import numpy as np
import pytest

from slam_sim.core.init_target import InitTarget, marker_board


def test_one_by_one_board_is_the_target() -> None:
    target = InitTarget()
    (marker,) = marker_board(target, 1, 1, target.side_m, 0.05)
    np.testing.assert_allclose(marker.corners_m, target.corners_m)
    assert marker.marker_id == target.marker_id


def test_board_lies_in_the_target_plane_in_reading_order() -> None:
    target = InitTarget()
    board = marker_board(target, 3, 3, 0.3, 0.05)
    assert [m.marker_id for m in board] == list(range(9))
    normal = target.rotation[:, 2]
    corners = np.vstack([m.corners_m for m in board])
    np.testing.assert_allclose((corners - target.centre_m) @ normal, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.mean([m.centre_m for m in board], axis=0), target.centre_m)
    right, up = target.rotation[:, 0], target.rotation[:, 1]
    # marker 0 is top left, marker 2 top right, marker 6 bottom left, 0.35 m pitch
    np.testing.assert_allclose((board[2].centre_m - board[0].centre_m) @ right, 0.7)
    np.testing.assert_allclose((board[0].centre_m - board[6].centre_m) @ up, 0.7)
    # markers do not overlap: the gap stays between neighbours' edges
    np.testing.assert_allclose(
        (board[1].corners_m[0] - board[0].corners_m[1]) @ right, 0.05, atol=1e-12
    )


@pytest.mark.parametrize(('rows', 'columns', 'gap'), [(0, 3, 0.0), (3, -1, 0.0), (2, 2, -0.1)])
def test_board_rejects_bad_shapes(rows: int, columns: int, gap: float) -> None:
    with pytest.raises(ValueError, match=r'board|gap_m'):
        marker_board(InitTarget(), rows, columns, 0.3, gap)
