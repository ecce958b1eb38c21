"""monoslam's known points from a depth image or a file (``known_points_source``), ROS-free:
each feature's depth read robustly from a registered depth image, the pairing of feature
frames with depth images in either arrival order, the start from them, the file's rows
matched by pixel whatever ids the tracker gives, and bad input named."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from monoslam_shadow_node.common.core.inputs import Features
from monoslam_shadow_node.monoslam.conversions import depth_from_image
from monoslam_shadow_node.monoslam.core.monoslam_types import TRACKING, WAITING, MonoSlamConfig
from monoslam_shadow_node.monoslam.known_points_input import (
    DepthImage,
    assign_known_points,
    read_known_points,
)
from monoslam_shadow_node.monoslam.processor import MonoSlamProcessor, MonoSlamStep
from slam_core.camera import CameraModel
from slam_core.depth import sample_depth

CAMERA = CameraModel(
    640, 480, np.array([[500.0, 0, 320.0], [0, 500.0, 240.0], [0, 0, 1]]), np.zeros(5)
)  # fmt: skip
MS = 1_000_000
RNG = np.random.default_rng(11)
POINTS = np.column_stack([RNG.uniform(-1.5, 1.5, (60, 2)), RNG.uniform(2.5, 4.0, 60)])
"""A static scene in front of the camera, which starts at the origin looking along +z."""


def _wall_depth(z_m: float = 3.0) -> np.ndarray:
    return np.full((480, 640), z_m)


def _centre(index: int) -> np.ndarray:
    return np.array([0.004 * index, 0.001 * index, 0.0])


def _features(index: int, ids: np.ndarray | None = None, offset: int = 0) -> Features:
    pixels = CAMERA.project(POINTS - _centre(index))
    track_ids = np.arange(len(POINTS)) + offset if ids is None else ids
    return Features(index * 33 * MS, 'camera', track_ids.astype(np.int64), pixels)


def _depth_of_points(stamp_ns: int) -> DepthImage:
    """A depth image that holds each point's depth in a 9 x 9 patch around its pixel (the
    rest: no depth), as a registered RGB-D camera would see small objects."""
    depth = np.full((480, 640), np.nan)
    pixels = np.rint(CAMERA.project(POINTS)).astype(int)
    for (u, v), z in zip(pixels, POINTS[:, 2], strict=True):
        depth[max(v - 4, 0) : v + 5, max(u - 4, 0) : u + 5] = z
    return DepthImage(stamp_ns, 'camera', depth)


def _steps(outcomes: list) -> list[MonoSlamStep]:
    return [o for o in outcomes if isinstance(o, MonoSlamStep)]


def test_a_feature_depth_is_the_window_median_and_none_across_an_edge_or_a_hole() -> None:
    """The processor reads depths with slam_core.depth.sample_depth, the importers' rule."""
    depth = _wall_depth()
    depth[:, 320:] = 1.0  # a step edge at u = 320
    depth[100:110, 100:110] = 0.0  # a hole (no depth)
    depth[300, 500] = 2.0  # a pixel off the surface: the window is not one surface
    depth[50, 501] = 0.0  # one missing pixel beside the feature's: the median of the rest
    pixels = np.array([[200.0, 200], [320, 200], [104, 104], [500, 300], [-5, 0], [500, 50]])
    z = sample_depth(depth, pixels)
    assert z[0] == 3.0 and z[5] == 1.0
    assert np.isnan(z[1]) and np.isnan(z[2]) and np.isnan(z[3]) and np.isnan(z[4])
    # a slanted floor (60 deg from the line of sight) keeps its depth
    slant = 3.0 + (np.arange(480)[:, None] - 240) * 3.0 / 500.0 * np.tan(np.radians(60))
    z = sample_depth(np.repeat(slant, 640, axis=1), np.array([[320.0, 300.0]]))
    np.testing.assert_allclose(z, slant[300, 0])


def _depth_processor() -> MonoSlamProcessor:
    config = MonoSlamConfig(known_points_source='depth', initialize='all', min_new_spacing_px=0.0)
    processor = MonoSlamProcessor(
        config, target_text='depth', sync_horizon_ns=200 * MS, depth_tolerance_ns=20 * MS
    )
    processor.set_camera(CAMERA)
    return processor


@pytest.mark.parametrize('depth_first', [True, False])
def test_the_depth_start_pairs_a_frame_with_its_depth_in_either_order(depth_first: bool) -> None:
    """Frames before the first depth image cannot start and are dropped, counted; the frame
    whose depth comes 14 ms after it starts the filter whichever arrives first; later depth
    images are not needed; the world is the start camera's frame."""
    processor = _depth_processor()
    processor.add_features(_features(0))  # no depth image will pair with it
    depth = _depth_of_points(33 * MS + 14 * MS)
    if depth_first:
        processor.add_depth(depth)
        outcomes = processor.add_features(_features(1))
    else:
        assert not _steps(processor.add_features(_features(1)))  # held for its depth
        outcomes = processor.add_depth(depth)
    steps = _steps(outcomes)
    assert processor.counts.dropped == {'no_depth': 1}
    assert [s.result.status for s in steps] == [TRACKING]
    assert steps[0].transition == 'started' and len(steps[0].result.added_ids) > 10
    for index in range(2, 30):
        steps = _steps(processor.add_features(_features(index)))
        processor.add_depth(_depth_of_points(index * 33 * MS + 14 * MS))
    assert steps[-1].result.status == TRACKING
    error = np.linalg.norm(steps[-1].result.centre - (_centre(29) - _centre(1)))
    assert error < 0.02  # metres: the depth fixed the scale
    assert processor.counts.depth_unused == 28 and processor.counts.depth_received == 29


def test_depth_images_are_decoded_only_while_needed_and_in_order() -> None:
    """A depth image given as a decoder is decoded only while the filter waits for one; one
    that does not decode, or is not after the last held one, is dropped and counted."""
    processor = _depth_processor()
    decoded: list[int] = []

    def decoder(stamp_ns: int):  # type: ignore[no-untyped-def]
        def decode() -> DepthImage:
            decoded.append(stamp_ns)
            return _depth_of_points(stamp_ns)

        return decode

    def broken() -> DepthImage:
        raise ValueError("encoding 'rgb8'")

    processor.add_depth(broken)
    processor.add_depth(decoder(47 * MS))
    processor.add_depth(decoder(40 * MS))  # older than the one held
    assert processor.counts.dropped == {'bad_depth': 1, 'depth_out_of_order': 1}
    processor.add_features(_features(1))  # 33 ms: pairs with the depth image at 47 ms
    assert processor.status == TRACKING
    processor.add_depth(decoder(80 * MS))
    assert decoded == [47 * MS, 40 * MS]  # not the one that came while tracking
    assert processor.counts.depth_received == 4 and processor.counts.depth_unused == 1


def test_frames_wait_at_most_the_horizon_for_a_depth_image() -> None:
    processor = _depth_processor()
    for index in range(8):  # 33 ms apart: the horizon (200 ms) passes
        processor.add_features(_features(index))
    assert processor.counts.dropped == {'no_depth': 1}  # frame 0: 231 ms before frame 7
    assert processor.status == WAITING
    processor.flush()  # the inputs stopped: no depth image will come
    assert processor.counts.dropped == {'no_depth': 8} and processor.counts.processed == 0


def _rows_file(tmp_path: Path) -> Path:
    pixels = CAMERA.project(POINTS[:8])
    lines = ['id,x,y,z,u,v'] + [
        f'{100 + k},{x},{y},{z},{u},{v}'
        for k, ((x, y, z), (u, v)) in enumerate(zip(POINTS[:8], pixels, strict=True))
    ]
    path = tmp_path / 'known.csv'
    path.write_text('\n'.join(lines) + '\n')
    return path


def _file_run(tmp_path: Path, offset: int) -> np.ndarray:
    rows = read_known_points(_rows_file(tmp_path))
    config = MonoSlamConfig(known_points=rows.known_points(), known_points_source='file')
    processor = MonoSlamProcessor(config, known_rows=rows, match_px=2.0)
    processor.set_camera(CAMERA)
    centres = []
    for index in range(20):
        for step in _steps(processor.add_features(_features(index, offset=offset))):
            centres.append(step.result.centre)
    assert processor.status == TRACKING and len(processor.assigned) == 8
    return np.array(centres)


def test_file_known_points_match_by_pixel_whatever_the_track_ids(tmp_path: Path) -> None:
    """The same run with the tracker's ids renumbered gives the same poses."""
    first, renumbered = _file_run(tmp_path, 0), _file_run(tmp_path, 5000)
    np.testing.assert_array_equal(first, renumbered)
    np.testing.assert_allclose(first[-1], _centre(19), atol=0.02)


def test_assignment_is_one_to_one_and_within_the_distance(tmp_path: Path) -> None:
    rows = read_known_points(_rows_file(tmp_path))
    features = _features(0)
    near = Features(0, 'camera', np.array([7, 8]), np.vstack([rows.pixels[0] + 1.0] * 2))
    assert assign_known_points(rows, near, 2.0) == {7: 100}  # one track per row
    assert assign_known_points(rows, features, 0.5) == {k: 100 + k for k in range(8)}


@pytest.mark.parametrize(
    ('text', 'message'),
    [
        ('x,y,z\n', 'header must be'),
        ('id,x,y,z,u,v\n1,0,0,1,2\n', ':2: 5 columns'),
        ('id,x,y,z,u,v\n1,0,0,1,2,a\n', ':2:'),
        ('id,x,y,z,u,v\n1,0,0,nan,2,3\n', ':2: values must be finite'),
        ('id,x,y,z,u,v\n1,0,0,1,2,3\n1,0,0,1,2,3\n', ':3: id 1 given twice'),
        ('id,x,y,z,u,v\n1,0,0,1,2,3\n', '1 known points, at least 4'),
    ],
)
def test_a_bad_known_points_file_is_named_with_its_line(
    tmp_path: Path, text: str, message: str
) -> None:
    path = tmp_path / 'bad.csv'
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_known_points(path)


def _image(encoding: str, data: bytes, bigendian: bool = False) -> SimpleNamespace:
    header = SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=5), frame_id='camera')
    size = 2 if encoding == '16UC1' else 4
    return SimpleNamespace(
        header=header, height=2, width=3, step=3 * size, encoding=encoding,
        is_bigendian=bigendian, data=data,
    )  # fmt: skip


def test_depth_images_in_millimetres_and_metres_read_the_same() -> None:
    millimetres = np.array([[1000, 0, 2500], [3000, 1234, 4000]], dtype='<u2')
    metres = np.where(millimetres > 0, millimetres / 1000.0, np.nan).astype('<f4')
    a = depth_from_image(_image('16UC1', millimetres.tobytes()))
    b = depth_from_image(_image('32FC1', metres.tobytes()))
    c = depth_from_image(_image('16UC1', millimetres.astype('>u2').tobytes(), bigendian=True))
    np.testing.assert_allclose(a.depth_m, b.depth_m, rtol=1e-6)
    np.testing.assert_array_equal(a.depth_m, c.depth_m)
    assert a.stamp_ns == 1_000_000_005 and np.isnan(a.depth_m[0, 1])
    with pytest.raises(ValueError, match="encoding 'rgb8'"):
        depth_from_image(_image('rgb8', b''))
    with pytest.raises(ValueError, match='do not hold it'):
        depth_from_image(_image('16UC1', b'\0' * 5))
