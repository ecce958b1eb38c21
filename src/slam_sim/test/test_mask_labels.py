"""Track labels from motion masks (``slam_sim.core.mask_labels``): a track's pixel at a mask,
the nearest-surface rule at unknown pixels, the tracks' own motion, the majority rule, and the
synthetic sequence's board and wall tracks end to end."""

from __future__ import annotations

import numpy as np
import pytest

from slam_core.camera import CameraModel
from slam_sim.core.depth_labels import MOVING, STATIC, UNKNOWN, PoseError
from slam_sim.core.mask_labels import (
    MaskLabelRule,
    MaskSightings,
    TrackSightings,
    label_by_masks,
    mask_sightings,
    motion_codes,
    sighting_codes,
)
from slam_sim.core.motion_masks import MaskedFrame

CAMERA = CameraModel.from_intrinsics(160, 120, (150.0, 150.0), (80.0, 60.0), (0.0,) * 5)


def _masked(mask: np.ndarray, depth_m: np.ndarray, x_m: float = 0.0, k: int = 0) -> MaskedFrame:
    pose = np.eye(4)
    pose[0, 3] = x_m
    return MaskedFrame(3 * k, k * 100_000_000, pose, depth_m, mask.astype(np.int8))


def test_a_track_is_taken_at_the_mask_image_or_moved_on_by_its_velocity() -> None:
    images = np.array([4, 5, 6, 4, 5, 7, 8, 7])
    ids = np.array([1, 1, 1, 2, 2, 3, 3, 4])  # the mask is at image 6
    pixels = np.array(
        [[10.0, 10], [12, 10], [14, 10], [50, 50], [54, 50], [80, 80], [81, 82], [90, 90]]
    )
    tracks = TrackSightings.of(images, ids, pixels)
    np.testing.assert_allclose(tracks.velocities[:3], [[2, 0], [2, 0], [2, 0]])
    np.testing.assert_allclose(tracks.velocities[5:7], [[1, 2], [1, 2]])  # from the next
    assert np.isnan(tracks.velocities[7]).all()  # seen once
    seen, at = tracks.at_image(6, max_gap_images=1)
    assert seen.tolist() == [1, 2, 3]  # 4 has no velocity to be moved to image 6 with
    np.testing.assert_allclose(at, [[14, 10], [58, 50], [79, 78]])
    assert tracks.at_image(6, max_gap_images=0)[0].tolist() == [1]
    assert tracks.at_image(20, max_gap_images=1)[0].size == 0


def test_an_unknown_pixel_takes_the_nearest_surface_around_it() -> None:
    """A person (moving, 1.5 m) in front of a wall (static, 3 m), an undecided band between;
    and a static pole (1 m) in front of the person."""
    mask = np.full((120, 160), STATIC)
    depth = np.full((120, 160), 3.0)
    mask[:, 60:100], depth[:, 60:100] = MOVING, 1.5
    mask[:, 56:60] = mask[:, 100:104] = UNKNOWN  # the depth edges
    mask[:, 78:82], depth[:, 78:82] = STATIC, 1.0  # the pole
    mask[:, 76:78] = mask[:, 82:84] = UNKNOWN
    pixels = np.array([[58.0, 50], [102, 50], [77, 50], [30, 50], [70, 50], [200, 50]])
    codes = sighting_codes(_masked(mask, depth), pixels, radius_px=4)
    assert codes.tolist() == [MOVING, MOVING, STATIC, STATIC, MOVING, UNKNOWN]
    far = np.full((120, 160), UNKNOWN)
    assert sighting_codes(_masked(far, depth), pixels[:1], radius_px=4).tolist() == [UNKNOWN]


def test_the_tracks_own_motion_tells_a_sliding_surface() -> None:
    """Points 2 m away seen from x = 0 and x = 5 cm: a static one where the poses put it,
    one 8 px off (3 cm along x on the surface); the chi-square bound holds its rate."""
    rng = np.random.default_rng(5)
    rule = MaskLabelRule(pixel_sigma_px=0.5, pose_error=PoseError.constant(0.0))
    pixels = np.column_stack([rng.uniform(20, 140, 2000), rng.uniform(20, 100, 2000)])
    depth = np.full(2000, 2.0)
    first = _masked(np.zeros((120, 160)), np.full((120, 160), 2.0))
    second = _masked(np.zeros((120, 160)), np.full((120, 160), 2.0), x_m=0.05, k=1)
    moved = pixels - [150.0 * 0.05 / 2.0, 0.0]  # where a static point is seen from x = 5 cm
    noisy = moved + 0.5 * rng.standard_normal(moved.shape)
    noisy_first = pixels + 0.5 * rng.standard_normal(pixels.shape)
    codes = motion_codes(CAMERA, (first, noisy_first, depth), (second, noisy), rule)
    assert np.mean(codes == MOVING) < 0.01  # 0.27 % expected
    slid = moved + np.array([8.0, 0.0])
    codes = motion_codes(CAMERA, (first, pixels, depth), (second, slid), rule)
    assert np.all(codes == MOVING)
    codes = motion_codes(CAMERA, (first, pixels, np.full(2000, np.nan)), (second, slid), rule)
    assert np.all(codes == UNKNOWN)  # no depth, no prediction


def test_a_track_is_moving_when_most_of_its_decided_sightings_are() -> None:
    ids = np.array([1, 1, 1, 2, 2, 2, 2, 3])
    codes = np.array([MOVING, MOVING, STATIC, MOVING, STATIC, STATIC, UNKNOWN, UNKNOWN])
    images = np.arange(len(ids))
    sightings = MaskSightings(ids, images, codes, codes, np.full(len(ids), UNKNOWN))
    labels = label_by_masks(np.array([3, 2, 1, 4]), sightings, MaskLabelRule())
    assert labels.ids.tolist() == [1, 2, 3, 4]
    assert labels.labels.tolist() == [MOVING, STATIC, UNKNOWN, UNKNOWN]
    np.testing.assert_allclose(labels.statistics[:2], [2 / 3, 1 / 3])
    assert labels.depth_sightings.tolist() == [3, 3, 0, 0]
    assert labels.counts()['unknown_no_depth'] == 2


def test_a_sighting_is_moving_when_its_mask_or_its_motion_is() -> None:
    """Three masks of a plane 2 m away, seen from x = 0, 5 and 10 cm (3.75 px apart), static
    but for an undecided patch; track 1 static, track 2 slides 8 px on the plane between
    masks, track 3 lies in the undecided patch, track 4 slips once (between masks 0 and 1)."""
    mask = np.full((120, 160), STATIC)
    mask[20:50, 120:150] = UNKNOWN
    depth = np.full((120, 160), 2.0)
    frames = [_masked(mask, depth, x_m=0.05 * k, k=k) for k in range(3)]
    start = np.array([[40.0, 60], [100, 60], [135, 35], [40, 90]])
    slide = np.array([[0.0, 0], [8, 0], [0, 0], [0, 0]])
    slip = np.array([[0.0, 0], [0, 0], [0, 0], [8, 0]])
    pixels = np.vstack([start, start - 3.75 + slide + slip, start - 7.5 + 2 * slide + slip])
    pixels[:, 1] = np.tile(start[:, 1], 3)  # the camera moves along x only
    ids = np.tile([1, 2, 3, 4], 3)
    images = np.repeat([0, 3, 6], 4)
    rule = MaskLabelRule(pose_error=PoseError.constant(0.0))
    sightings = mask_sightings(CAMERA, TrackSightings.of(images, ids, pixels), frames, rule)
    assert sightings.ids.tolist() == ids.tolist()
    assert sightings.mask_codes.tolist() == [STATIC, STATIC, UNKNOWN, STATIC] * 3
    assert sightings.motion_codes.tolist() == [
        *(STATIC, MOVING, STATIC, UNKNOWN),  # 4's one slip is not taken
        *(STATIC, MOVING, STATIC, STATIC),
        *(UNKNOWN,) * 4,  # no later mask
    ]
    assert sightings.codes.tolist() == [
        *(STATIC, MOVING, STATIC, STATIC),
        *(STATIC, MOVING, STATIC, STATIC),
        *(STATIC, STATIC, UNKNOWN, STATIC),
    ]
    labels = label_by_masks(ids, sightings, rule)
    assert labels.labels.tolist() == [STATIC, MOVING, STATIC, STATIC]
    depth_only = label_by_masks(ids, sightings.depth_only(), rule)
    assert depth_only.labels.tolist() == [STATIC, STATIC, UNKNOWN, STATIC]
    with pytest.raises(ValueError, match='share'):
        MaskLabelRule(share=0.0)
    assert rule.bound == pytest.approx(11.829, abs=1e-3)  # chi2(2) at 0.9973
