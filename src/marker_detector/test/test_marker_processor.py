"""marker_detector glue without ROS: images, settings, static transforms, processor errors."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from marker_detector.core.frame_types import ExtrinsicsConfig, InputError, StaticTransforms
from marker_detector.detector.processor import MarkerProcessor
from marker_detector.detector.settings import (
    PARAMETERS,
    detector_config,
    parse_id_ranges,
    parse_marker_sizes,
)
from slam_core.errors import ParameterError
from slam_core.images import ImageError, decode_compressed, decode_raw

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'marker_detector.yaml'


def defaults() -> dict[str, object]:
    return dict(PARAMETERS.defaults())


# --- images ---------------------------------------------------------------------------------


def test_decode_raw_reads_every_supported_encoding_with_row_padding() -> None:
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 255, (5, 7, 3), dtype=np.uint8)
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    padded = np.zeros((5, 7 * 3 + 3), np.uint8)
    padded[:, : 7 * 3] = bgr.reshape(5, -1)
    np.testing.assert_array_equal(decode_raw('bgr8', 7, 5, 24, padded.tobytes()), gray)
    rgb = bgr[..., ::-1].copy()
    np.testing.assert_array_equal(decode_raw('rgb8', 7, 5, 21, rgb.tobytes()), gray)
    np.testing.assert_array_equal(decode_raw('mono8', 7, 5, 7, gray.tobytes()), gray)


@pytest.mark.parametrize(
    ('encoding', 'width', 'height', 'step', 'size', 'message'),
    [
        ('yuv422', 4, 4, 8, 32, "unsupported image encoding 'yuv422'"),
        ('mono8', 0, 0, 0, 0, 'empty image'),
        ('mono8', 4, 4, 4, 10, 'image data has 10 bytes'),
        ('bgr8', 4, 4, 8, 48, 'row step 8 < width 4 x 3 bytes'),
    ],
)
def test_decode_raw_names_the_problem(
    encoding: str, width: int, height: int, step: int, size: int, message: str
) -> None:
    with pytest.raises(ImageError, match=message):
        decode_raw(encoding, width, height, step, bytes(size))


def test_decode_compressed_round_trips_and_rejects_corrupt_data() -> None:
    image = np.tile(np.arange(64, dtype=np.uint8), (48, 1))
    ok, png = cv2.imencode('.png', image)
    assert ok
    np.testing.assert_array_equal(decode_compressed('png', png.tobytes()), image)
    with pytest.raises(ImageError, match='empty compressed image'):
        decode_compressed('jpeg', b'')
    with pytest.raises(ImageError, match='cannot decode compressed image'):
        decode_compressed('jpeg', b'\xff\xd8\xff' + bytes(100))


# --- settings -------------------------------------------------------------------------------


def test_marker_sizes_and_id_ranges_parse_and_reject_with_the_entry() -> None:
    assert parse_marker_sizes(['7:0.14', '12:0.2']) == {7: 0.14, 12: 0.2}
    with pytest.raises(ValueError, match=r"entry '7=0\.14'"):
        parse_marker_sizes(['7=0.14'])
    with pytest.raises(ValueError, match='id 7 given twice'):
        parse_marker_sizes(['7:0.1', '7:0.2'])
    assert parse_id_ranges(['3', '0-2', '2']) == (0, 1, 2, 3)
    with pytest.raises(ValueError, match="entry '5-2'"):
        parse_id_ranges(['5-2'])
    with pytest.raises(ValueError, match="entry 'x'"):
        parse_id_ranges(['x'])


@pytest.mark.parametrize(
    ('name', 'value'),
    [('marker_size_m', 0.0), ('marker_size_m', -0.1), ('marker_sizes_m', ['3:-1.0'])],
)
def test_a_zero_or_negative_marker_size_is_rejected_naming_it(name: str, value: object) -> None:
    values = defaults() | {name: value}
    with pytest.raises(ParameterError, match=rf'^parameter marker_detector\.{name}='):
        detector_config(values)


def test_the_shipped_yaml_configures_the_defaults() -> None:
    values = PARAMETERS.read_yaml(CONFIG)
    assert detector_config(values) == detector_config(defaults())


def test_a_yaml_with_an_unknown_key_is_rejected_naming_it(tmp_path: Path) -> None:
    path = tmp_path / 'bad.yaml'
    path.write_text('/**:\n  ros__parameters:\n    marker_size: 0.2\n', encoding='utf-8')
    with pytest.raises(ParameterError) as caught:
        PARAMETERS.read_yaml(path)
    assert str(path) in str(caught.value)
    assert "'marker_size' is not a parameter of node marker_detector" in str(caught.value)
    assert "did you mean 'marker_size_m'?" in str(caught.value)


# --- static transforms and the processor -----------------------------------------------------


def transform(xyz: tuple[float, float, float], rpy: tuple[float, float, float]) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler('xyz', rpy).as_matrix()
    matrix[:3, 3] = xyz
    return matrix


def test_static_transforms_chain_and_invert_between_branches() -> None:
    tree = StaticTransforms()
    base_camera = transform((0.1, 0.0, 1.0), (0.0, 0.2, 0.0))
    camera_optical = transform((0.0, 0.0, 0.0), (-math.pi / 2, 0.0, -math.pi / 2))
    base_laser = transform((0.3, 0.1, 0.2), (0.0, 0.0, 0.5))
    tree.add('base_link', 'camera_link', base_camera)
    tree.add('camera_link', 'camera_optical_frame', camera_optical)
    tree.add('/base_link', 'laser', base_laser)
    np.testing.assert_allclose(
        tree.lookup('base_link', 'camera_optical_frame'), base_camera @ camera_optical, atol=1e-12
    )
    np.testing.assert_allclose(
        tree.lookup('laser', 'camera_optical_frame'),
        np.linalg.inv(base_laser) @ base_camera @ camera_optical,
        atol=1e-12,
    )
    assert tree.lookup('base_link', 'unknown_frame') is None


def test_extrinsics_settings_are_validated() -> None:
    with pytest.raises(ValueError, match='extrinsics_source'):
        ExtrinsicsConfig(source='urdf')
    with pytest.raises(ValueError, match='camera_xyz_m'):
        ExtrinsicsConfig(source='parameters', camera_xyz_m=(0.0, math.nan, 0.0))


def test_the_processor_names_a_missing_camera_info_and_a_missing_mount() -> None:
    processor = MarkerProcessor(detector_config(defaults()), ExtrinsicsConfig())
    image = np.zeros((480, 640), np.uint8)
    with pytest.raises(InputError, match='no camera_info received yet'):
        processor.process(1, 'camera_optical_frame', image)
    k = [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0]
    processor.set_camera_info('camera_optical_frame', 640, 480, k, [0.0] * 5, 'plumb_bob')
    with pytest.raises(InputError, match="no static transform from 'base_link' to the camera"):
        processor.process(1, 'camera_optical_frame', image)
    with pytest.raises(InputError, match='camera_info'):
        processor.set_camera_info('camera_optical_frame', 640, 480, [0.0] * 9, [], 'plumb_bob')
    processor.transforms.add('base_link', 'camera_optical_frame', np.eye(4))
    assert processor.process(1, 'camera_optical_frame', image).detections == []
    with pytest.raises(InputError, match='image at 2 ns'):
        processor.process(2, 'camera_optical_frame', np.zeros((10, 10), np.uint8))
