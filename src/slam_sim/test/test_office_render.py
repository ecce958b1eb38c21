"""The office camera renderer: exact marker corners, occlusion, the camera and seeded effects."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from slam_core.camera import CameraModel
from slam_core.render.rays import ray_grid
from slam_sim.core.camera_effects import CameraEffects, ImageEffects, encode_jpeg
from slam_sim.core.office_render import Renderer
from slam_sim.core.office_view import (
    LevelPose,
    Markers,
    MarkerTruth,
    SceneStyle,
    marker_texture,
    office_camera,
)

CAMERA = office_camera()
STYLE = SceneStyle()
# A 10 m x 8 m room; the camera stands in it at 1 m height looking east (+x).
ROOM = np.array(
    [
        [[0.0, 0.0], [10.0, 0.0]],
        [[10.0, 0.0], [10.0, 8.0]],
        [[10.0, 8.0], [0.0, 8.0]],
        [[0.0, 8.0], [0.0, 0.0]],
    ]
)
POSE = LevelPose(np.array([2.0, 4.0, 1.0]), 0.0)
# Detectable markers in front of the camera: (id, x m, y m, z m, facing yaw rad).
MARKERS = (
    (0, 4.0, 4.3, 1.1, math.pi),
    (7, 3.8, 4.8, 0.95, math.pi - 0.5),
    (42, 5.0, 2.8, 1.25, math.pi + 0.4),
    (105, 3.0, 3.8, 0.75, math.pi - 0.2),
    (300, 6.0, 3.7, 1.6, math.pi + 0.3),
)
NO_EFFECTS = ImageEffects(
    gain_drift=(0.0, 0.0),
    gain_jitter=0.0,
    offset_drift=0.0,
    vignetting=0.0,
    defocus_sigma_px=(0.0, 0.0),
    exposure_s=0.0,
    read_noise=0.0,
    shot_noise=0.0,
)


def _markers(rows: tuple[tuple[int, float, float, float, float], ...]) -> Markers:
    table = np.array(rows, dtype=np.float64).reshape(-1, 5)
    return Markers(
        ids=table[:, 0].astype(np.int64),
        centers_m=table[:, 1:4],
        normals=np.column_stack([np.cos(table[:, 4]), np.sin(table[:, 4])]),
    )


def _detect(image: np.ndarray) -> dict[int, np.ndarray]:
    """Marker id -> corners (4, 2) px found by OpenCV's aruco detector with subpixel corners."""
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    corners, ids, _ = cv2.aruco.ArucoDetector(dictionary, parameters).detectMarkers(image)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners, strict=True)}


def _truth_of(truth: MarkerTruth, marker_id: int) -> int:
    return int(np.nonzero(truth.ids == marker_id)[0][0])


def test_undistort_inverts_the_distortion_over_the_image() -> None:
    rays = ray_grid(CAMERA)
    v, u = np.mgrid[0 : CAMERA.height : 7, 0 : CAMERA.width : 7]
    normalized = np.column_stack([rays.x_u[v, u].ravel(), rays.y_u[v, u].ravel()])
    pixels = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
    np.testing.assert_allclose(
        CAMERA.distort_normalized(normalized.astype(np.float64)), pixels, atol=1e-3
    )


def test_the_office_camera_and_its_scaled_copies() -> None:
    info = CAMERA.camera_info()
    assert (info.width, info.height, info.distortion_model) == (640, 480, 'plumb_bob')
    np.testing.assert_array_equal(info.k, [457.0, 0, 321.3, 0, 457.0, 238.4, 0, 0, 1])
    assert info.d.tolist() == [-0.1, 0.02, 4e-4, -3e-4, 0.0]
    assert office_camera(640, 480) == CAMERA
    assert office_camera(320, 240).fx == pytest.approx(CAMERA.fx / 2)
    with pytest.raises(ValueError, match=r'not in \[16, 8192\]'):
        office_camera(8, 480)


def _corner_errors(found: dict[int, np.ndarray], truth: MarkerTruth) -> dict[int, float]:
    """Marker id -> (largest corner error px, side px) of each detected marker."""
    errors = {}
    for marker_id, corners in found.items():
        k = _truth_of(truth, marker_id)
        errors[marker_id] = float(np.linalg.norm(corners - truth.corners_px[k], axis=1).max())
    return errors


def test_rendered_markers_are_found_at_their_true_corners() -> None:
    image, truth = Renderer(CAMERA, ROOM, STYLE).render(POSE, _markers(MARKERS))
    found = _detect(np.clip(np.rint(image), 0, 255).astype(np.uint8))
    assert set(found) == {row[0] for row in MARKERS} == set(truth.ids[truth.visible].tolist())
    for marker_id, error_px in _corner_errors(found, truth).items():
        side_px = truth.side_px[_truth_of(truth, marker_id)]
        assert side_px >= 30.0
        # aruco's corners sit up to ~0.2 px inside the square; more on small markers.
        assert error_px < (0.5 if side_px >= 45.0 else 0.8), marker_id


def test_markers_survive_the_image_effects_and_jpeg() -> None:
    image, truth = Renderer(CAMERA, ROOM, STYLE).render(POSE, _markers(MARKERS))
    effects = CameraEffects(ImageEffects(), CAMERA, np.random.SeedSequence(3))
    noisy = effects.apply(image, frame_index=5, time_s=12.0, yaw_rate_radps=0.3)
    decoded = cv2.imdecode(np.frombuffer(encode_jpeg(noisy, 65), np.uint8), cv2.IMREAD_GRAYSCALE)
    found = _detect(decoded)
    assert set(found) == {row[0] for row in MARKERS}
    for marker_id, error_px in _corner_errors(found, truth).items():
        side_px = truth.side_px[_truth_of(truth, marker_id)]
        assert error_px < (0.6 if side_px >= 45.0 else 1.5), marker_id


@pytest.mark.parametrize(('distance_m', 'lateral_m'), [(0.8, 0.0), (1.5, 0.5), (3.0, 1.1)])
def test_the_rendered_edge_is_where_the_projection_puts_it(
    distance_m: float, lateral_m: float
) -> None:
    """The left edge of the black square, found to 0.05 px by the ink it puts in one image
    row (an area estimate, unbiased by the antialiasing), lies on the projected 3D edge."""
    center = [POSE.position_m[0] + distance_m, POSE.position_m[1] + lateral_m, 1.03]
    image, truth = Renderer(CAMERA, ROOM, STYLE).render(
        POSE, Markers(np.array([0]), np.array([center]), np.array([[-1.0, 0.0]]))
    )
    corners = truth.corners_px[0]
    row = round(0.5 * (corners[0, 1] + corners[3, 1]))
    # The 3D left edge, sampled densely, projected; the true crossing of that image row.
    along = np.linspace(-0.5, 0.5, 20001) * STYLE.side_m
    edge = truth.translation_m[0] + np.outer(along, truth.rotation[0][:, 1])
    edge = edge - 0.5 * STYLE.side_m * truth.rotation[0][:, 0]
    pixels = CAMERA.project(edge)
    crossing = float(np.interp(row, pixels[::-1, 1], pixels[::-1, 0]))
    cell_px = truth.side_px[0] / 8.0
    first, last = math.floor(crossing - 0.6 * cell_px), math.ceil(crossing + 0.6 * cell_px)
    ink = (STYLE.paper - image[row, first : last + 1]) / (STYLE.paper - STYLE.ink)
    assert last + 0.5 - float(ink.sum()) == pytest.approx(crossing, abs=0.05)


def test_truth_pose_gives_the_corners_in_the_marker_frame_convention() -> None:
    _, truth = Renderer(CAMERA, ROOM, STYLE).render(POSE, _markers(MARKERS[:1]))
    half = 0.5 * STYLE.side_m
    square = half * np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]], dtype=float)
    points = truth.translation_m[0] + square @ truth.rotation[0].T
    np.testing.assert_allclose(CAMERA.project(points), truth.corners_px[0], atol=1e-9)
    # Facing the camera: marker z points back at it, x right and y up in the image.
    np.testing.assert_allclose(truth.rotation[0][:, 2], [0.0, 0.0, -1.0], atol=1e-12)
    top_left, top_right, _, bottom_left = truth.corners_px[0]
    assert top_right[0] > top_left[0] and bottom_left[1] > top_left[1]


def test_a_wall_hides_a_marker_and_a_wall_edge_hides_part_of_one() -> None:
    behind = ((1, 5.0, 4.0, 1.0, math.pi), (2, 5.0, 5.0, 1.0, math.pi))
    screen = np.concatenate([ROOM, [[[3.5, 3.0], [3.5, 4.5]]]])
    plain, _ = Renderer(CAMERA, screen, STYLE).render(POSE, _markers(()))
    image, truth = Renderer(CAMERA, screen, STYLE).render(POSE, _markers(behind))
    hidden, partly = _truth_of(truth, 1), _truth_of(truth, 2)
    assert truth.in_image[hidden] and not truth.visible[hidden]
    assert truth.visible_fraction[hidden] == 0.0
    assert 0.0 < truth.visible_fraction[partly] < 1.0 and not truth.visible[partly]
    column = round(float(truth.corners_px[hidden, :, 0].mean()))
    np.testing.assert_array_equal(image[:, column], plain[:, column])
    assert set(_detect(np.clip(np.rint(image), 0, 255).astype(np.uint8))) == set()


def test_a_nearer_marker_hides_a_farther_one_and_backs_are_not_drawn() -> None:
    rows = (
        (3, 6.0, 4.0, 1.0, math.pi),  # far
        (4, 3.5, 4.0, 1.0, math.pi),  # near, in front of marker 3
        (5, 4.0, 5.2, 1.0, 0.0),  # facing away
    )
    image, truth = Renderer(CAMERA, ROOM, STYLE).render(POSE, _markers(rows))
    plain, _ = Renderer(CAMERA, ROOM, STYLE).render(POSE, _markers(rows[:2]))
    far, near, back = (_truth_of(truth, i) for i in (3, 4, 5))
    assert truth.visible[near] and not truth.visible[far]
    assert truth.visible_fraction[far] == 0.0
    assert not truth.visible[back] and truth.in_image[back]
    np.testing.assert_array_equal(image, plain)


def test_markers_outside_the_view_or_behind_the_camera() -> None:
    rows = ((8, 1.0, 4.0, 1.0, 0.0), (9, 3.0, 7.9, 1.0, -0.5 * math.pi))
    _, truth = Renderer(CAMERA, ROOM, STYLE).render(POSE, _markers(rows))
    assert 8 not in truth.ids.tolist()  # behind the camera: no truth at all
    side = _truth_of(truth, 9)
    assert not truth.in_image[side] and not truth.visible[side]


def test_effects_are_deterministic_for_a_seed_and_frame() -> None:
    image, _ = Renderer(CAMERA, ROOM, STYLE).render(POSE, _markers(MARKERS))

    def apply(seed: int, frame: int) -> np.ndarray:
        effects = CameraEffects(ImageEffects(), CAMERA, np.random.SeedSequence(seed))
        return effects.apply(image.copy(), frame_index=frame, time_s=3.0, yaw_rate_radps=0.2)

    np.testing.assert_array_equal(apply(11, 2), apply(11, 2))
    assert np.any(apply(11, 2) != apply(11, 3))
    assert np.any(apply(11, 2) != apply(12, 2))
    clean = CameraEffects(NO_EFFECTS, CAMERA, np.random.SeedSequence(0))
    plain = clean.apply(image, frame_index=0, time_s=0.0, yaw_rate_radps=1.0)
    np.testing.assert_array_equal(plain, np.clip(np.rint(image), 0, 255).astype(np.uint8))


def test_turning_blurs_along_the_image_rows() -> None:
    image, _ = Renderer(CAMERA, ROOM, STYLE).render(POSE, _markers(MARKERS))
    effects = CameraEffects(
        ImageEffects(read_noise=0.0, shot_noise=0.0), CAMERA, np.random.SeedSequence(0)
    )

    def row_sharpness(yaw_rate_radps: float) -> float:
        out = effects.apply(image, frame_index=0, time_s=0.0, yaw_rate_radps=yaw_rate_radps)
        return float(np.percentile(np.abs(np.diff(out.astype(np.float64), axis=1)), 99.5))

    assert row_sharpness(1.0) < 0.7 * row_sharpness(0.0)


def test_invalid_inputs_are_rejected() -> None:
    with pytest.raises(ValueError, match='not in DICT_APRILTAG_36h11'):
        marker_texture(600, STYLE)
    with pytest.raises(ValueError, match='not invertible'):
        ray_grid(CameraModel(640, 480, CAMERA.K, np.array([-1.5, 0.0, 0.0, 0.0, 0.0])))
    with pytest.raises(ValueError, match='walls'):
        Renderer(CAMERA, np.zeros((0, 2, 2)), STYLE)
    with pytest.raises(ValueError, match='quality'):
        encode_jpeg(np.zeros((8, 8), np.uint8), 0)
