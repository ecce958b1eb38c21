"""marker_detector core: known answers on synthetic renders, configs, gates, covariance."""

from __future__ import annotations

import dataclasses
import math
import re

import cv2
import numpy as np
import pytest

from marker_detector.core.base_frame import to_range_bearing
from marker_detector.core.candidates import locate_markers
from marker_detector.core.decoding import decode_quad
from marker_detector.core.detection import (
    DetectionResult,
    MarkerDetection,
    detect_markers,
    make_detector,
)
from marker_detector.core.detector_config import DetectorConfig
from marker_detector.core.dictionaries import DICTIONARIES, get_dictionary
from marker_detector.core.pose import (
    corner_jacobian,
    marker_object_points,
    pose_covariance,
    solve_marker_pose,
    solve_marker_poses,
)
from marker_detector.core.rendering import MarkerPlacement, render_markers
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import log_rotation
from slam_core.geometry.se3 import optical_from_link, transform_from_xyz_rpy
from slam_core.geometry.so3 import rotation_from_vector
from slam_core.testing.jacobians import assert_jacobian_close, numerical_jacobian

K_640 = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
PLUMB_BOB = np.array([-0.28, 0.09, 0.0008, -0.0006, -0.01])
RATIONAL = np.array([0.4, -0.2, 0.0005, 0.0004, 0.02, 0.7, -0.25, 0.05])
FACING = np.diag([1.0, -1.0, -1.0])  # marker face towards the camera, printed upright


def camera(d: np.ndarray | None = None, model: str = 'plumb_bob') -> CameraModel:
    return CameraModel(640, 480, K_640, np.zeros(5) if d is None else d, model)


def tilted(rx: float = 0.0, ry: float = 0.0, rz: float = 0.0) -> np.ndarray:
    """Marker rotation: facing the camera, then turned by (rx, ry, rz) rad about camera axes."""
    return rotation_from_vector(np.array([rx, ry, rz])) @ FACING


def snapshot(
    cam: CameraModel,
    placements: list[MarkerPlacement],
    rng: np.random.Generator,
    *,
    blur_px: float = 0.7,
    noise: float = 1.5,
    background: float = 110.0,
) -> np.ndarray:
    """Render, blur, add noise and quantize like a camera."""
    image = render_markers(cam, placements, background)
    image = cv2.GaussianBlur(image, (0, 0), blur_px) + rng.normal(0.0, noise, image.shape)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def detect_one(image: np.ndarray, cam: CameraModel, config: DetectorConfig) -> MarkerDetection:
    result = detect_markers(image, cam, config)
    assert len(result.detections) == 1, f'{result.detections} {result.rejections}'
    return result.detections[0]


def angle_between_deg(first: np.ndarray, second: np.ndarray) -> float:
    return math.degrees(float(np.linalg.norm(log_rotation(first @ second.T))))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20260521)


# --- dictionaries -------------------------------------------------------------------------


def test_every_supported_dictionary_loads_with_its_marker_size() -> None:
    sizes = {'DICT_APRILTAG_36h11': 6, 'DICT_APRILTAG_25h9': 5, 'DICT_APRILTAG_16h5': 4,
             'DICT_APRILTAG_36h10': 6, 'DICT_ARUCO_ORIGINAL': 5}  # fmt: skip
    sizes |= {f'DICT_{n}X{n}_{c}': n for n in range(4, 8) for c in (50, 100, 250, 1000)}
    assert set(DICTIONARIES) == set(sizes)
    assert {name: get_dictionary(name).markerSize for name in DICTIONARIES} == sizes


def test_unknown_dictionary_is_named_with_the_valid_ones() -> None:
    with pytest.raises(ValueError, match=r"'DICT_APRILTAG_36h12'.*DICT_APRILTAG_36h11"):
        get_dictionary('DICT_APRILTAG_36h12')


def _min_hamming_distance(dictionary: cv2.aruco.Dictionary) -> int:
    size = dictionary.markerSize
    codes = [
        np.rot90(
            cv2.aruco.Dictionary.getBitsFromByteList(dictionary.bytesList[i : i + 1], size), k
        )
        for i in range(len(dictionary.bytesList))
        for k in range(4)
    ]
    flat = np.array([c.ravel() for c in codes], dtype=np.int16)  # 4 rotations per marker
    best = size * size
    for i in range(0, len(flat), 4):
        others = np.delete(flat, np.s_[i : i + 4], axis=0)
        best = min(best, int(np.min(np.sum(flat[i] != others, axis=1))))
        best = min(best, *(int(np.sum(flat[i] != flat[i + k])) for k in range(1, 4)))
    return best


@pytest.mark.parametrize(
    ('name', 'hamming'), [('DICT_APRILTAG_16h5', 5), ('DICT_APRILTAG_25h9', 9)]
)
def test_apriltag_families_correct_what_their_hamming_distance_allows(
    name: str, hamming: int
) -> None:
    dictionary = get_dictionary(name)
    assert _min_hamming_distance(dictionary) == hamming
    assert dictionary.maxCorrectionBits == (hamming - 1) // 2
    stock = cv2.aruco.getPredefinedDictionary(DICTIONARIES[name]).maxCorrectionBits
    assert stock in (0, dictionary.maxCorrectionBits)  # 0 on OpenCV 4.x, fixed in 5.x


def test_36h11_code_with_three_bit_errors_is_still_identified() -> None:
    dictionary = get_dictionary('DICT_APRILTAG_36h11')
    bits = cv2.aruco.Dictionary.getBitsFromByteList(dictionary.bytesList[7:8], 6).copy()
    bits[0, 0], bits[2, 3], bits[5, 1] = 1 - bits[0, 0], 1 - bits[2, 3], 1 - bits[5, 1]
    found, marker_id, _ = dictionary.identify(bits, 0.6)  # 0.6 * 5 bits -> 3
    assert found and marker_id == 7
    stock = cv2.aruco.getPredefinedDictionary(DICTIONARIES['DICT_APRILTAG_36h11'])
    if stock.maxCorrectionBits == 0:  # OpenCV 4.x: its stock dictionary corrects nothing
        assert not stock.identify(bits, 0.6)[0]


# --- configuration and input validation ---------------------------------------------------


@pytest.mark.parametrize(
    ('name', 'value'),
    [
        ('dictionary', 'DICT_9X9_50'),
        ('default_marker_size_m', 0.0),
        ('default_marker_size_m', math.inf),
        ('marker_sizes_m', {3: -0.1}),
        ('marker_sizes_m', {-1: 0.1}),
        ('corner_refinement', 'bilinear'),
        ('min_side_px', -1.0),
        ('max_reprojection_error_px', 0.0),
        ('max_range_m', math.nan),
        ('max_viewing_angle_rad', 2.0),
        ('allowed_ids', (1, -2)),
        ('pixel_noise_px', 0.0),
        ('error_correction_rate', 1.5),
        ('detector_profile', 'turbo'),
    ],
)
def test_invalid_setting_is_rejected_by_name(name: str, value: object) -> None:
    with pytest.raises(ValueError, match=rf'^marker_detector setting {name}='):
        DetectorConfig(**{name: value})  # type: ignore[arg-type]


def test_limits_may_be_infinite_and_sizes_are_per_id() -> None:
    config = DetectorConfig(max_range_m=math.inf, marker_sizes_m={4: 0.3}, allowed_ids=[1, 4])  # type: ignore[arg-type]
    assert config.marker_size_m(4) == 0.3 and config.marker_size_m(5) == 0.16
    assert config.allowed_ids == (1, 4)


@pytest.mark.parametrize(
    ('image', 'message'),
    [
        (np.zeros((0, 640), np.uint8), 'empty'),
        (np.zeros((480, 640), np.uint16), 'dtype is uint16'),
        (np.zeros((480, 640), np.float32), 'dtype is float32'),
        (np.zeros((480, 640, 4), np.uint8), r'shape \(480, 640, 4\)'),
        (np.zeros((240, 320), np.uint8), '320x240 px but camera_info says 640x480'),
        ([[0, 1]], 'numpy array'),
    ],
)
def test_bad_images_are_rejected_clearly(image: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        detect_markers(image, camera(), DetectorConfig())  # type: ignore[arg-type]


# --- detection and pose on synthetic images -----------------------------------------------


@pytest.mark.parametrize(
    ('d', 'model'),
    [(None, 'plumb_bob'), (PLUMB_BOB, 'plumb_bob'), (RATIONAL, 'rational_polynomial')],
)
def test_known_pose_gives_id_corners_pose_and_range(
    d: np.ndarray | None, model: str, rng: np.random.Generator
) -> None:
    cam = camera(d, model)
    placement = MarkerPlacement(42, 0.16, tilted(0.3, -0.5, 0.2), np.array([0.45, -0.25, 1.8]))
    image = snapshot(cam, [placement], rng)
    detection = detect_one(image, cam, DetectorConfig())
    truth_corners = placement.corners_px(cam)
    assert detection.id == 42 and detection.dictionary == 'DICT_APRILTAG_36h11'
    assert np.max(np.linalg.norm(detection.corners_px - truth_corners, axis=1)) < 0.1
    true_range = float(np.linalg.norm(placement.translation_m))
    assert abs(detection.range_m / true_range - 1.0) < 0.0025
    assert np.linalg.norm(detection.translation_m - placement.translation_m) < 0.01
    assert angle_between_deg(detection.rotation, placement.rotation) < 1.0
    assert detection.rotation[2, 2] < 0  # the marker's z axis points back at the camera
    assert detection.side_px == pytest.approx(
        np.min(np.linalg.norm(truth_corners - np.roll(truth_corners, -1, axis=0), axis=1)), abs=0.2
    )
    assert detection.reprojection_error_px < 0.1
    assert detection.viewing_angle_rad == pytest.approx(
        math.acos(-placement.rotation[:, 2] @ placement.translation_m / true_range), abs=0.01
    )


def test_range_error_below_half_a_percent_over_random_poses(rng: np.random.Generator) -> None:
    cam = camera(PLUMB_BOB)
    config = DetectorConfig(max_range_m=math.inf)
    detector = make_detector(config)
    range_errors, corner_errors = [], []
    for _ in range(12):
        distance = rng.uniform(1.0, 3.0)  # sides of 25-80 px
        placement = MarkerPlacement(
            int(rng.integers(0, 587)),
            0.16,
            tilted(*rng.uniform(-0.6, 0.6, 3)),
            np.array([*rng.uniform(-0.25, 0.25, 2) * distance, distance]),
        )
        image = snapshot(cam, [placement], rng, background=float(rng.uniform(60, 200)))
        result = detect_markers(image, cam, config, detector)
        assert [d.id for d in result.detections] == [placement.marker_id]
        detection = result.detections[0]
        range_errors.append(detection.range_m / np.linalg.norm(placement.translation_m) - 1)
        corner_errors.extend(
            np.linalg.norm(detection.corners_px - placement.corners_px(cam), axis=1)
        )
    assert np.max(np.abs(range_errors)) < 0.005  # measured 0.23 %
    assert np.median(corner_errors) < 0.05  # measured 0.014 px


def test_edge_fit_removes_the_inward_bias_of_opencv_corners(rng: np.random.Generator) -> None:
    cam = camera()
    placements = [
        MarkerPlacement(i, 0.16, tilted(*rng.uniform(-0.4, 0.4, 3)),
                        np.array([*rng.uniform(-0.5, 0.5, 2), rng.uniform(2.0, 3.0)]))
        for i in range(4)
    ]  # fmt: skip
    images = [snapshot(cam, [p], rng) for p in placements]

    def radial_bias(config: DetectorConfig) -> float:
        outward = []
        for placement, image in zip(placements, images, strict=True):
            (marker,) = locate_markers(image, config, make_detector(config), cam)
            truth = placement.corners_px(cam)
            direction = truth - truth.mean(axis=0)
            direction /= np.linalg.norm(direction, axis=1)[:, None]
            outward.extend(np.sum((marker.corners_px - truth) * direction, axis=1))
        return float(np.mean(outward))

    assert radial_bias(DetectorConfig(edge_refinement=False)) < -0.1  # corners sit inside
    assert abs(radial_bias(DetectorConfig())) < 0.05


def test_gray_and_bgr_images_give_the_same_detections(rng: np.random.Generator) -> None:
    cam = camera()
    image = snapshot(cam, [MarkerPlacement(3, 0.16, tilted(0.2), np.array([0.0, 0.0, 1.5]))], rng)
    gray = detect_markers(image, cam, DetectorConfig())
    bgr = detect_markers(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), cam, DetectorConfig())
    np.testing.assert_allclose(gray.detections[0].corners_px, bgr.detections[0].corners_px)


def test_marker_sizes_are_taken_per_id(rng: np.random.Generator) -> None:
    cam = camera()
    placements = [
        MarkerPlacement(1, 0.16, tilted(), np.array([-0.3, 0.0, 2.0])),
        MarkerPlacement(2, 0.30, tilted(), np.array([0.4, 0.0, 2.5])),
    ]
    config = DetectorConfig(marker_sizes_m={2: 0.30})
    result = detect_markers(snapshot(cam, placements, rng), cam, config)
    ranges = {d.id: d.range_m for d in result.detections}
    assert ranges[1] == pytest.approx(np.linalg.norm(placements[0].translation_m), rel=0.005)
    assert ranges[2] == pytest.approx(np.linalg.norm(placements[1].translation_m), rel=0.005)
    assert {d.id: d.marker_size_m for d in result.detections} == {1: 0.16, 2: 0.30}


@pytest.fixture(scope='module')
def gate_scene() -> tuple[CameraModel, np.ndarray]:
    cam = camera()
    placements = [
        MarkerPlacement(7, 0.16, tilted(0.0, 0.9, 0.0), np.array([0.35, 0.0, 1.5])),  # 38 deg
        MarkerPlacement(8, 0.16, tilted(0.1), np.array([-0.35, 0.1, 2.5])),
    ]
    return cam, snapshot(cam, placements, np.random.default_rng(1))


@pytest.mark.parametrize(
    ('settings', 'rejected', 'reason'),
    [
        ({'allowed_ids': (8,)}, [7], r'^id 7 not in allowed_ids$'),
        ({'min_side_px': 32.5}, [8], r'^side 31\.\d px < min_side_px 32\.5$'),
        ({'max_reprojection_error_px': 1e-4}, [7, 8], r'reprojection error .* px > max_repr'),
        ({'max_range_m': 2.0}, [8], r'^range 2\.5\d m > max_range_m 2$'),
        (
            {'max_viewing_angle_rad': 0.5},
            [7],
            r'^viewing angle 38\.\d deg > max_viewing_angle_rad 0\.5 \(28\.6 deg\)$',
        ),
    ],
)
def test_each_quality_gate_rejects_with_a_reason(
    gate_scene: tuple[CameraModel, np.ndarray],
    settings: dict[str, object],
    rejected: list[int],
    reason: str,
) -> None:
    cam, image = gate_scene
    result: DetectionResult = detect_markers(image, cam, DetectorConfig(**settings))  # type: ignore[arg-type]
    assert sorted(r.id for r in result.rejections) == rejected
    assert sorted(d.id for d in result.detections) == sorted({7, 8} - set(rejected))
    for rejection in result.rejections:
        assert rejection.corners_px is not None and rejection.corners_px.shape == (4, 2)
        assert re.search(reason, rejection.reason), rejection.reason
        assert rejection.gate == next(iter(settings))  # the setting that dropped it


def test_candidates_far_below_the_side_gate_are_not_even_decoded(
    gate_scene: tuple[CameraModel, np.ndarray],
) -> None:
    """cv2.aruco skips contours whose sides cannot reach min_side_px (less the 2 px slack of
    rough corners): marker 8 (32 px) is neither detected nor reported; marker 7 (smallest
    side 43 px) is within the slack of the 45 px gate and is rejected with its reason."""
    cam, image = gate_scene
    result = detect_markers(image, cam, DetectorConfig(min_side_px=45.0))
    assert result.detections == []
    assert [(r.id, r.gate) for r in result.rejections] == [(7, 'min_side_px')]
    default = detect_markers(image, cam, DetectorConfig())
    assert sorted(d.id for d in default.detections) == [7, 8]  # the floor follows the gate


def test_a_rejected_candidate_is_decoded_from_refined_corners(rng: np.random.Generator) -> None:
    cam = camera()
    placement = MarkerPlacement(11, 0.16, tilted(0.2, 0.3), np.array([0.1, 0.0, 1.6]))
    image = snapshot(cam, [placement], rng).astype(np.float32)
    truth = placement.corners_px(cam)
    dictionary = get_dictionary('DICT_APRILTAG_36h11')
    for start in range(4):  # any starting corner, clockwise on screen
        decoded = decode_quad(image, np.roll(truth, -start, axis=0), dictionary)
        assert decoded is not None and decoded[0] == 11
        np.testing.assert_allclose(decoded[1], truth)
    assert decode_quad(image, truth + np.array([60.0, 0.0]), dictionary) is None  # background


# --- covariance ---------------------------------------------------------------------------


def test_both_ippe_solutions_match_opencvs_solvepnp_ippe_square(
    rng: np.random.Generator,
) -> None:
    """The batched numpy IPPE gives cv2.solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)'s poses (before
    the Gauss-Newton step) for noisy corners through a distorted lens, and its alternative
    error is that of cv2's other solution (cv2's RMS is per coordinate, ours per corner: a
    factor sqrt(2)); degenerate (collinear) corners give no pose."""
    cam = camera(np.array([-0.12, 0.05, 0.001, -0.002, 0.0]))
    corners, sizes, references = [], [], []
    for _ in range(30):
        size = float(rng.uniform(0.05, 0.3))
        rotation = tilted(*rng.uniform(-0.8, 0.8, 3))
        translation = np.array(
            [rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), rng.uniform(0.5, 4)]
        )
        objects = marker_object_points(size)
        pixels = cam.project(objects @ rotation.T + translation) + rng.normal(0, 0.3, (4, 2))
        _, rvecs, tvecs, errors = cv2.solvePnPGeneric(
            objects, pixels.reshape(4, 1, 2), cam.K, cam.dist_coeffs,
            flags=cv2.SOLVEPNP_IPPE_SQUARE,
        )  # fmt: skip
        corners.append(pixels)
        sizes.append(size)
        references.append((rvecs, tvecs, np.ravel(errors)))
    poses = solve_marker_poses(np.array(corners), sizes, cam, refine_iterations=0)
    for pose, (rvecs, tvecs, errors) in zip(poses, references, strict=True):
        assert pose is not None
        best, other = np.argsort(errors)[:2]
        assert log_rotation(pose.rotation) == pytest.approx(np.ravel(rvecs[best]), abs=1e-4)
        assert pose.translation_m == pytest.approx(np.ravel(tvecs[best]), abs=1e-5)
        per_corner = math.sqrt(2.0) * errors
        assert pose.reprojection_error_px == pytest.approx(per_corner[best], rel=1e-3, abs=1e-4)
        assert pose.alternative_error_px == pytest.approx(per_corner[other], rel=1e-3, abs=1e-4)
    line = np.array([[[100.0, 100.0], [200.0, 100.0], [300.0, 100.0], [400.0, 100.0]]])
    flat = solve_marker_poses(line, [0.1], cam)[0]
    assert flat is None or flat.reprojection_error_px > 10.0


def test_corner_jacobian_matches_finite_differences_of_the_left_perturbation() -> None:
    cam = camera(PLUMB_BOB)
    objects = marker_object_points(0.16)
    rotation, translation = tilted(0.4, -0.3, 0.2), np.array([0.3, -0.2, 1.7])

    def corners(x: np.ndarray) -> np.ndarray:
        moved = rotation_from_vector(x[3:]) @ rotation
        return cam.project(objects @ moved.T + translation + x[:3]).ravel()

    jacobian = corner_jacobian(objects, rotation, translation, cam)
    assert_jacobian_close(jacobian, corners, np.zeros(6), atol=1e-4, rtol=1e-5)


def test_covariance_is_symmetric_psd_and_scales_with_pixel_noise(
    rng: np.random.Generator,
) -> None:
    cam = camera()
    image = snapshot(cam, [MarkerPlacement(5, 0.16, tilted(0.4), np.array([0.2, 0.1, 2.0]))], rng)
    covariances = [
        detect_one(image, cam, DetectorConfig(pixel_noise_px=sigma)).covariance
        for sigma in (0.5, 1.0)
    ]
    for covariance in covariances:
        assert covariance.shape == (6, 6)
        np.testing.assert_array_equal(covariance, covariance.T)
        assert np.min(np.linalg.eigvalsh(covariance)) > 0
    np.testing.assert_allclose(covariances[1], 4.0 * covariances[0], rtol=1e-9)


def test_covariance_matches_monte_carlo_of_noisy_corners(rng: np.random.Generator) -> None:
    cam = camera(PLUMB_BOB)
    objects = marker_object_points(0.16)
    # 80 px marker tilted 0.6 rad: the mirror IPPE pose explains the corners 2.9 px worse, so
    # 0.5 px noise never flips the pose (a flip is a different, far, solution)
    rotation, translation = tilted(0.6, 0.3, 0.1), np.array([0.2, -0.1, 1.0])
    exact = cam.project(objects @ rotation.T + translation)
    sigma = 0.5
    pose = solve_marker_pose(exact, 0.16, cam)
    assert pose is not None and pose.alternative_error_px > 2.5
    predicted = pose_covariance(pose.jacobian, sigma)
    assert predicted is not None
    samples = []
    for _ in range(400):
        noisy = solve_marker_pose(exact + rng.normal(0.0, sigma, exact.shape), 0.16, cam)
        assert noisy is not None
        d_theta = log_rotation(noisy.rotation @ pose.rotation.T)  # left perturbation
        samples.append(np.concatenate([noisy.translation_m - pose.translation_m, d_theta]))
    sampled = np.cov(np.array(samples).T)
    ratio = np.sqrt(np.diag(sampled) / np.diag(predicted))  # sigma sampled / predicted
    assert np.all(np.abs(ratio - 1.0) < 0.15), ratio
    nees = np.mean([s @ np.linalg.solve(predicted, s) for s in samples])
    assert 6.0 * 0.85 < nees < 6.0 * 1.15


# --- base frame ---------------------------------------------------------------------------


def _detection_at(translation: np.ndarray, covariance: np.ndarray) -> MarkerDetection:
    return MarkerDetection(
        id=9, dictionary='DICT_APRILTAG_36h11', corners_px=np.zeros((4, 2)),
        rotation=FACING, translation_m=translation, covariance=covariance,
        reprojection_error_px=0.1, marker_size_m=0.16, side_px=40.0,
        range_m=float(np.linalg.norm(translation)), viewing_angle_rad=0.0,
    )  # fmt: skip


def test_range_bearing_of_a_camera_mounted_with_offset_and_yaw() -> None:
    # camera_link 0.2 m ahead, 0.1 m left, 0.5 m up, yawed 30 deg left, pitched 10 deg down
    base_from_optical = (
        transform_from_xyz_rpy([0.2, 0.1, 0.5], [0.0, math.radians(10.0), math.radians(30.0)])
        @ optical_from_link()
    )
    marker_in_base = np.array([2.0, 1.5, 0.3])
    in_optical = np.linalg.solve(base_from_optical, [*marker_in_base, 1.0])[:3]
    assert in_optical[2] > 0  # in front of the camera
    covariance = np.diag([1e-4, 4e-4, 9e-4, 1e-3, 1e-3, 1e-3])
    observation = to_range_bearing(_detection_at(in_optical, covariance), base_from_optical)
    assert observation.id == 9
    assert observation.range_m == pytest.approx(2.5, abs=1e-12)  # hypot(2.0, 1.5)
    assert observation.bearing_rad == pytest.approx(math.atan2(1.5, 2.0), abs=1e-12)

    def range_bearing(position: np.ndarray) -> np.ndarray:
        moved = to_range_bearing(_detection_at(position, covariance), base_from_optical)
        return np.array([moved.range_m, moved.bearing_rad])

    jacobian = numerical_jacobian(range_bearing, in_optical)
    expected = jacobian @ covariance[:3, :3] @ jacobian.T
    np.testing.assert_allclose(observation.covariance, expected, rtol=1e-6, atol=1e-12)
    np.testing.assert_array_equal(observation.covariance, observation.covariance.T)


def test_range_bearing_rejects_a_malformed_transform() -> None:
    detection = _detection_at(np.array([0.0, 0.0, 2.0]), np.eye(6) * 1e-4)
    with pytest.raises(ValueError, match='T_base_camera must be a finite 4x4'):
        to_range_bearing(detection, np.eye(3))


def test_detection_to_range_bearing_end_to_end(rng: np.random.Generator) -> None:
    cam = camera(PLUMB_BOB)
    base_from_optical = transform_from_xyz_rpy([0.1, 0.0, 0.3], [0, 0, 0]) @ optical_from_link()
    marker_in_base = np.array([2.2, -0.6, 0.35])
    in_optical = np.linalg.solve(base_from_optical, [*marker_in_base, 1.0])[:3]
    placement = MarkerPlacement(
        21, 0.16, optical_from_link()[:3, :3].T @ tilted_in_base(), in_optical
    )
    detection = detect_one(snapshot(cam, [placement], rng), cam, DetectorConfig())
    observation = to_range_bearing(detection, base_from_optical)
    assert observation.range_m == pytest.approx(math.hypot(2.2, -0.6), rel=0.005)
    assert math.degrees(abs(observation.bearing_rad - math.atan2(-0.6, 2.2))) < 0.1
    sigma_range, sigma_bearing = np.sqrt(np.diag(observation.covariance))
    assert 0.001 < sigma_range < 0.05 and 1e-4 < sigma_bearing < 0.01


def tilted_in_base() -> np.ndarray:
    """R_base_marker of a marker on a wall facing the robot, turned 20 deg about base z."""
    facing_robot = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    return transform_from_xyz_rpy([0, 0, 0], [0, 0, math.radians(20.0)])[:3, :3] @ facing_robot


def test_dataclass_config_is_frozen() -> None:
    config = DetectorConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.max_range_m = 3.0  # type: ignore[misc]
