"""The image-level dynamic scene (core.dynamic_render): geometry against the measurement-level
simulation, labels, the target under cv2.aruco, and features a tracker can follow."""

from __future__ import annotations

from collections.abc import Callable
from functools import cache

import cv2
import numpy as np
import pytest

from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_options import RenderOptions
from slam_sim.core.dynamic_render import (
    DEFAULT_OBJECT_RADIUS_M,
    LABEL_NOTHING,
    LABEL_STATIC,
    DynamicRenderer,
    RenderedFrame,
)
from slam_sim.core.dynamic_scene import observe
from slam_sim.core.init_target import InitTarget, target_pixels
from slam_sim.core.office_view import SceneStyle

CONFIG = DynamicSceneConfig(duration_s=12.0)
# Plain, cheap textures for tests that only look at geometry and labels.
PLAIN = RenderOptions(texels_per_m=10.0, patches_per_m2=0.0, object_face_texels=16, effects=None)
FrameSource = Callable[[int], RenderedFrame]


@cache
def _renderer(seed: int = 0) -> DynamicRenderer:
    return DynamicRenderer(CONFIG, seed)


@pytest.fixture(scope='module')
def frame() -> FrameSource:
    """Frames of the seed-0 run, rendered once each."""
    return cache(_renderer().render)


def _interior(mask: np.ndarray, margin_px: int) -> np.ndarray:
    """The uint8 mask of pixels at least ``margin_px`` inside ``mask``."""
    kernel = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)
    return np.asarray(cv2.erode(mask.astype(np.uint8), kernel))


def test_static_points_are_drawn_at_their_depth_on_static_surfaces(frame: FrameSource) -> None:
    renderer = _renderer()
    checked = hidden = 0
    for k in (0, 90, 180, 270):
        rotation, centre = renderer.pose(k)
        points = (renderer.scene.static_points_m - centre) @ rotation
        seen, pixels = observe(renderer.camera, points, CONFIG)
        depth_true = points[seen, 2]
        depth, labels = renderer.probe(k, pixels[seen])
        on_surface = np.abs(depth - depth_true) < 1e-4 * depth_true
        occluded = depth < depth_true - 1e-4 * depth_true  # behind a cabinet, object or board
        assert np.all(on_surface | occluded)
        assert np.all(labels[on_surface] == LABEL_STATIC)
        # The rendered maps agree at the nearest pixel centre (depth changes across it).
        nearest = np.rint(pixels[seen][on_surface]).astype(int)
        image = frame(k)
        map_depth = image.depth_m[nearest[:, 1], nearest[:, 0]]
        map_label = image.labels[nearest[:, 1], nearest[:, 0]]
        agree = (np.abs(map_depth - depth_true[on_surface]) < 0.02 * depth_true[on_surface]) & (
            map_label == LABEL_STATIC
        )
        assert agree.mean() > 0.95
        checked += int(on_surface.sum())
        hidden += int(occluded.sum())
    assert checked > 300 and hidden < checked


def test_probe_of_no_pixels_is_empty() -> None:
    depth, labels = _renderer().probe(0, np.zeros((0, 2)))
    assert depth.shape == (0,) and depth.dtype == np.float32
    assert labels.shape == (0,) and labels.dtype == np.int16


def test_objects_are_spheres_that_hide_the_room_behind_them(frame: FrameSource) -> None:
    renderer = _renderer()
    drawn = set()
    for k in (0, 100, 200, 300):
        rotation, position = renderer.pose(k)
        centres, exists = renderer.object_centres(k)
        points = (centres - position) @ rotation
        ahead = exists & (points[:, 2] > 1.0)
        depth, labels = renderer.probe(k, renderer.camera.project(points))
        distance = np.linalg.norm(centres - position, axis=1)
        front_depth = (distance - DEFAULT_OBJECT_RADIUS_M) * points[:, 2] / distance
        own = ahead & (labels == np.arange(len(labels)))
        np.testing.assert_allclose(depth[own], front_depth[own], rtol=1e-4)
        assert np.all(depth[ahead & ~own] < front_depth[ahead & ~own])  # hidden by something
        drawn.update(np.flatnonzero(own).tolist())
        image = frame(k)
        for index in np.unique(image.labels[image.labels >= 0]).tolist():
            mask = image.labels == index
            ring = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
            ring &= image.labels == LABEL_STATIC
            # The room around an object's outline lies behind it.
            assert np.median(image.depth_m[ring]) > image.depth_m[mask].max()
    assert drawn == {0, 1, 2, 3}


def test_an_object_is_drawn_from_its_birth_on_and_radius_zero_draws_the_default() -> None:
    config = DynamicSceneConfig(
        duration_s=6.0, motions=('model',), objects=30, object_radius_m=0.0
    )
    renderer = DynamicRenderer(config, 5, options=PLAIN)
    assert renderer.object_radius_m == DEFAULT_OBJECT_RADIUS_M
    births = [round(motion.appears_s * config.rate_hz) for motion in renderer.scene.objects]
    shown = 0
    for index, birth in enumerate(births):
        if birth <= 0:
            continue
        rotation, position = renderer.pose(birth)
        centre = renderer.object_centres(birth)[0][index]
        point = (centre - position) @ rotation
        if point[2] < 1.0:
            continue
        pixel = renderer.camera.project(point[None])
        if renderer.probe(birth, pixel)[1][0] != index:
            continue  # out of the image, out of the room or hidden
        assert renderer.object_centres(birth - 1)[1][index] == np.False_
        assert renderer.probe(birth - 1, pixel)[1][0] != index
        shown += 1
    assert shown >= 2


def test_the_target_is_detected_at_its_true_corners(frame: FrameSource) -> None:
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), parameters
    )
    errors = []
    for k in range(0, 360, 45):
        image = frame(k)
        assert image.target_corners_px is not None
        corners, ids, _ = detector.detectMarkers(image.image)
        assert ids is not None and ids.ravel().tolist() == [0]
        errors.append(np.linalg.norm(corners[0].reshape(4, 2) - image.target_corners_px, axis=1))
    assert np.sqrt(np.mean(np.square(errors))) < 0.5


def test_a_target_inside_a_cabinet_is_hidden_and_has_no_truth() -> None:
    config = DynamicSceneConfig(duration_s=1.0)
    room = _renderer().scene.room
    rotation, position = _renderer().pose(0)
    outcomes = []
    for low, high in zip(room.cabinets_min_m, room.cabinets_max_m, strict=True):
        side = 0.5 * float(min(high[1] - low[1], high[2] - low[2]))
        centre = 0.5 * (low + high)
        inside = InitTarget(side_m=side, centre_m=centre)
        ahead = np.array([0.5 * (high[0] - low[0]) + 0.3, 0.0, 0.0])
        in_front = InitTarget(side_m=side, centre_m=centre - ahead)
        if target_pixels(inside, _renderer().camera, rotation, position) is None:
            continue  # not in the image
        hidden = DynamicRenderer(config, 0, options=PLAIN, target=inside).render(0)
        shown = DynamicRenderer(config, 0, options=PLAIN, target=in_front).render(0)
        outcomes.append((hidden.target_corners_px is None, shown.target_corners_px is not None))
    assert outcomes and all(hidden for hidden, _ in outcomes)
    assert any(shown for _, shown in outcomes)


def test_the_target_edges_are_drawn_where_the_target_is() -> None:
    renderer = DynamicRenderer(CONFIG, 0, options=RenderOptions(effects=None))
    target, style = renderer.target, SceneStyle()
    half_grey = 0.5 * (style.ink + style.paper)
    axes = np.asarray(target.rotation)
    for k in (0, 315):
        image = renderer.render(k)
        for side in (-1.0, 1.0):  # the black square's left and right outer edges
            along = np.linspace(-0.4, 0.4, 17) * target.side_m
            edge = target.centre_m + side * 0.5 * target.side_m * axes[:, 0]
            points = edge + along[:, None] * axes[:, 1]
            pixels = renderer.camera.project((points - image.position_m) @ image.rotation)
            offsets = []
            for row in np.rint(pixels[2:-2, 1]).astype(int):
                column = np.interp(row, pixels[::-1, 1], pixels[::-1, 0])  # the true edge
                first = int(column) - 4
                profile = image.image[row, first : first + 9].astype(float)
                step = np.flatnonzero(np.diff(np.sign(profile - half_grey)))
                assert len(step) == 1
                i = int(step[0])
                crossing = first + i + (half_grey - profile[i]) / (profile[i + 1] - profile[i])
                offsets.append(crossing - column)
            assert abs(np.mean(offsets)) < 0.08 and np.std(offsets) < 0.2


def test_surfaces_look_the_same_after_their_true_motion_so_nothing_shimmers() -> None:
    renderer = DynamicRenderer(CONFIG, 0, options=RenderOptions(effects=None))
    height, width = renderer.camera.height, renderer.camera.width
    rows, columns = np.mgrid[0:height, 0:width]
    pixels = np.column_stack([columns.ravel(), rows.ravel()]).astype(np.float64)
    for k in (20, 260):
        image, following = renderer.render(k), renderer.render(k + 1)
        moved = _true_motion(renderer, image, pixels).reshape(height, width, 2).astype(np.float32)
        warped = cv2.remap(following.image.astype(np.float32), moved[..., 0], moved[..., 1],
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
        inside = np.all((moved > 3.0) & (moved < [width - 4.0, height - 4.0]), axis=2)
        static = _interior(image.labels == LABEL_STATIC, 2).astype(bool) & inside
        residual = image.image[static] - warped[static]
        assert np.sqrt(np.mean(residual**2)) < 6.5  # 8-10 without prefiltered textures


@pytest.mark.slow
def test_pixels_on_outlines_average_the_surfaces_they_cover() -> None:
    exact = DynamicRenderer(CONFIG, 0, options=RenderOptions(effects=None, supersample=8))
    reference = exact.render(140)
    near, far = (cv2.erode(reference.depth_m, np.ones((3, 3))), cv2.dilate(reference.depth_m,
                 np.ones((3, 3))))  # fmt: skip
    outline = far > 1.05 * near
    assert outline.sum() > 1000
    for supersample, limit in ((3, 4.0), (1, None)):
        options = RenderOptions(effects=None, supersample=supersample)
        image = DynamicRenderer(CONFIG, 0, options=options).render(140).image
        error = np.abs(image.astype(float) - reference.image)[outline].mean()
        assert error < limit if limit is not None else error > 8.0  # aliased without it


def test_the_same_seed_renders_the_same_frames(frame: FrameSource) -> None:
    again = DynamicRenderer(CONFIG, 0).render(7)
    np.testing.assert_array_equal(again.image, frame(7).image)
    np.testing.assert_array_equal(again.labels, frame(7).labels)
    other = DynamicRenderer(CONFIG, 1).render(7)
    assert np.mean(other.image != again.image) > 0.5


def test_good_features_lie_on_static_surfaces_and_on_every_object(frame: FrameSource) -> None:
    renderer = _renderer()
    for k in (30, 150, 270):
        image = frame(k)
        corners = cv2.goodFeaturesToTrack(image.image, 1000, 0.01, 7).reshape(-1, 2)
        labels = image.labels[
            np.rint(corners[:, 1]).astype(int), np.rint(corners[:, 0]).astype(int)
        ]
        assert np.count_nonzero(labels == LABEL_STATIC) > 400
        cells = np.histogram2d(*corners.T, bins=(4, 3), range=((0, 640), (0, 480)))[0]
        assert np.all(cells >= 10)  # spread over the whole image
        centres, exists = renderer.object_centres(k)
        distance = np.linalg.norm(centres - image.position_m, axis=1)
        for index in range(len(centres)):
            inside = _interior(image.labels == index, 2)  # not the silhouette
            if not exists[index] or not 3.0 <= distance[index] <= 8.0 or inside.sum() < 200:
                continue
            found = cv2.goodFeaturesToTrack(image.image, 50, 0.01, 3, mask=inside)
            assert found is not None and len(found) >= 3, (k, index)


def _true_motion(
    renderer: DynamicRenderer, image: RenderedFrame, pixels: np.ndarray
) -> np.ndarray:
    """Where the surface points at pixel centres ``pixels`` (N, 2) of ``image`` are in the
    next frame."""
    k = image.index
    columns, rows = np.rint(pixels).astype(int).T
    normalized, valid = renderer.camera.unproject(pixels)
    assert np.all(valid)
    depth = image.depth_m[rows, columns].astype(np.float64)[:, None]
    points = image.position_m + (np.column_stack([normalized, np.ones(len(depth))]) * depth) @ (
        image.rotation.T
    )
    labels = image.labels[rows, columns]
    before, after = renderer.object_centres(k)[0], renderer.object_centres(k + 1)[0]
    moved = np.where(labels[:, None] >= 0, (after - before)[np.maximum(labels, 0)], 0.0)
    rotation, position = renderer.pose(k + 1)
    return renderer.camera.project((points + moved - position) @ rotation)


def test_lucas_kanade_follows_the_true_image_motion(frame: FrameSource) -> None:
    renderer = _renderer()
    errors: dict[bool, list[float]] = {True: [], False: []}
    for k in (20, 140, 260):
        image, following = frame(k), frame(k + 1)
        static = _interior(image.labels == LABEL_STATIC, 4)
        moving = _interior(image.labels >= 0, 3)
        corners = [cv2.goodFeaturesToTrack(image.image, 300, 0.01, 7, mask=static)]
        corners.append(cv2.goodFeaturesToTrack(image.image, 60, 0.01, 3, mask=moving))
        start = np.vstack([c.reshape(-1, 2) for c in corners if c is not None])
        tracked, status, _ = cv2.calcOpticalFlowPyrLK(
            image.image, following.image, start, None, winSize=(15, 15), maxLevel=3
        )
        truth = _true_motion(renderer, image, start.astype(np.float64))
        on_object = image.labels[start[:, 1].astype(int), start[:, 0].astype(int)] >= 0
        error = np.linalg.norm(tracked - truth, axis=1)
        assert np.median(np.linalg.norm(truth - start, axis=1)) > 0.5  # the image moves
        for is_object in (True, False):
            errors[is_object] += error[(status.ravel() == 1) & (on_object == is_object)].tolist()
    for is_object, values in errors.items():
        assert len(values) > (50 if is_object else 500)
        assert np.median(values) < 0.15 and np.mean(np.array(values) < 0.5) > 0.95


def test_pixels_beyond_the_lens_fold_see_nothing() -> None:
    renderer = DynamicRenderer(
        DynamicSceneConfig(duration_s=1.0, focal_px=150.0), 0, options=PLAIN
    )
    image = renderer.render(0)
    assert image.labels[0, 0] == LABEL_NOTHING and image.labels[240, 320] != LABEL_NOTHING
    nothing = image.labels == LABEL_NOTHING
    assert np.all(np.isinf(image.depth_m[nothing])) and np.all(image.image[nothing] == 0)
    assert np.all(np.isfinite(image.depth_m[~nothing]))
    camera = renderer.camera
    pixels = np.array([[0.0, 0.0], [320.0, 240.0], [500.0, 300.0], [200.0, 400.0]])
    normalized, valid = camera.unproject(pixels)
    assert valid.tolist() == [False, True, True, True]
    rays = np.column_stack([normalized, np.ones(len(pixels))])
    np.testing.assert_allclose(camera.project(rays[valid]), pixels[valid], atol=1e-9)


@pytest.mark.parametrize(
    ('field', 'value'),
    [
        ('supersample', 0),
        ('mip_levels', 6),
        ('object_face_texels', 20),
        ('patch_size_m', (0.3, 0.1)),
    ],
)
def test_render_options_reject_values_naming_the_field(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        RenderOptions(**{field: value})  # type: ignore[arg-type]
