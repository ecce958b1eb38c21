"""What fuzzing the marker_detector's and apriltag_bridge's inputs found (tests/fuzz_nodes.py):
static transforms that close a loop made every later image raise out of the callback, and
transforms with NaN, inf or an all-zero quaternion were taken or raised."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from marker_detector.common.conversions import transform_matrix
from marker_detector.core.frame_types import InputError, StaticTransforms


def transform(xyz: tuple[float, ...], xyzw: tuple[float, ...]) -> SimpleNamespace:
    return SimpleNamespace(
        translation=SimpleNamespace(x=xyz[0], y=xyz[1], z=xyz[2]),
        rotation=SimpleNamespace(x=xyzw[0], y=xyzw[1], z=xyzw[2], w=xyzw[3]),
    )


def test_a_transform_closing_a_loop_is_refused_and_lookups_keep_working() -> None:
    tree = StaticTransforms()
    tree.add('base_link', 'camera_link', np.eye(4))
    tree.add('camera_link', 'camera_optical_frame', np.eye(4))
    with pytest.raises(InputError, match='would form a loop'):
        tree.add('camera_optical_frame', 'base_link', np.eye(4))
    with pytest.raises(InputError, match='would form a loop'):
        tree.add('/camera_optical_frame', '/camera_link', np.eye(4))  # re-parenting too
    assert tree.lookup('base_link', 'camera_optical_frame') is not None  # used to raise
    assert tree.lookup('base_link', 'odom') is None


def test_a_non_finite_static_transform_is_refused() -> None:
    tree = StaticTransforms()
    bad = np.eye(4)
    bad[0, 3] = math.nan
    with pytest.raises(InputError, match='not 4x4 finite'):
        tree.add('base_link', 'camera_link', bad)
    assert tree.parents == {}


@pytest.mark.parametrize(
    ('xyz', 'xyzw', 'problem'),
    [
        ((math.nan, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 'translation'),
        ((0.0, math.inf, 0.0), (0.0, 0.0, 0.0, 1.0), 'translation'),
        ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), 'not a rotation'),
        ((0.0, 0.0, 0.0), (0.0, math.nan, 0.0, 1.0), 'not a rotation'),
        ((0.0, 0.0, 0.0), (0.0, 0.0, -math.inf, 1.0), 'not a rotation'),
    ],
)
def test_transform_matrix_refuses_what_is_no_rigid_transform(
    xyz: tuple[float, ...], xyzw: tuple[float, ...], problem: str
) -> None:
    with pytest.raises(InputError, match=problem):
        transform_matrix(transform(xyz, xyzw))


def test_transform_matrix_takes_unnormalized_and_huge_quaternions() -> None:
    for scale in (1e-300, 2.0, 1e300):  # 1e300 squared overflows a plain norm
        matrix = transform_matrix(transform((1.0, 2.0, 3.0), (0.0, 0.0, scale, scale)))
        assert np.all(np.isfinite(matrix))
        assert matrix[:3, :3] == pytest.approx(
            np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), abs=1e-12
        )
        assert matrix[:3, 3].tolist() == [1.0, 2.0, 3.0]
