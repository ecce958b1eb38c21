"""Per-pixel motion masks (``slam_sim.core.motion_masks``): the free-space rule on small depth
maps, thin structures under a pose error, the synthetic sequence's sliding board, and the real
bonn_crowd (its static opening and a walking person)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam_core.camera import CameraModel
from slam_core.depth import DepthSampling, sample_depth
from slam_core.testing.datasets import dataset_or_skip
from slam_sim.core.depth_labels import MOVING, STATIC, UNKNOWN, PoseError
from slam_sim.core.motion_masks import (
    DepthFrame,
    MaskRule,
    depth_edges,
    motion_mask,
    pair_votes,
    pixel_rays,
    sequence_masks,
)
from slam_sim.core.rgbd_depth import read_depth_m
from slam_sim.core.tum_rgbd import read_tum_rgbd
from slam_sim.core.tum_synthetic import SyntheticTum, board_mask, write_synthetic_tum

CAMERA = CameraModel.from_intrinsics(160, 120, (150.0, 150.0), (80.0, 60.0), (0.0,) * 5)
EXACT = MaskRule(pose_error=PoseError.constant(0.0), stride_px=1, opening_px=0)


def _frame(
    depth_m: np.ndarray, x_m: float = 0.0, rule: MaskRule = EXACT, k: int = 0
) -> DepthFrame:
    """A depth frame of CAMERA at x = ``x_m`` (optical frame = world frame), k * 0.1 s."""
    pose = np.eye(4)
    pose[0, 3] = x_m
    return DepthFrame.build(pixel_rays(CAMERA), depth_m, pose, k * 100_000_000, rule)


def _grid(frame: DepthFrame, values: np.ndarray) -> np.ndarray:
    """The per-usable-pixel ``values`` back on the (stride 1) image grid, False elsewhere."""
    out = np.zeros(frame.usable.shape, bool)
    out[frame.usable] = values
    return out


def test_depth_edges_are_the_pixels_robust_sampling_refuses() -> None:
    rng = np.random.default_rng(3)
    depth = np.full((60, 80), 3.0) + 0.01 * rng.standard_normal((60, 80))
    depth[20:40, 30:50] = 1.5  # a box in front
    depth[5:9, 5:9] = np.nan  # a hole
    us, vs = np.meshgrid(np.arange(80.0), np.arange(60.0))
    pixels = np.column_stack([us.ravel(), vs.ravel()])
    refused = np.isnan(sample_depth(depth, pixels, DepthSampling())).reshape(60, 80)
    np.testing.assert_array_equal(depth_edges(depth, DepthSampling()), refused)


def test_a_point_in_free_space_is_a_violation_and_an_occluded_one_is_no_evidence() -> None:
    """Frame k sees a box at A, frame j (same pose) sees it moved to B."""
    wall = np.full((120, 160), 3.0)
    before, after = wall.copy(), wall.copy()
    before[40:80, 20:60] = 1.5  # A
    after[40:80, 100:140] = 1.5  # B
    frame, other = _frame(before), _frame(after, k=1)
    votes = pair_votes(CAMERA, frame, other, EXACT)
    violation, support = _grid(frame, votes.violation), _grid(frame, votes.support)
    assert violation[45:75, 25:55].all()  # j saw the wall through where the box was
    assert not violation[45:75, 105:135].any()  # j's box hides k's wall: not motion ...
    assert not support[45:75, 105:135].any()  # ... and no support either
    assert support[5:30, 5:155].all() and not violation[5:30, 5:155].any()


def test_a_thin_pole_missed_by_the_pose_error_stays_static() -> None:
    """A pole 8 px wide 2 m in front of a wall 3 m away; frame j's true position is 2 cm to
    the side of the one given (a pose error): 1.5 px at the pole, so k's pole pixels land
    partly on the wall in j."""
    scene = np.full((120, 160), 3.0)
    scene[:, 76:84] = 2.0
    shifted = np.full((120, 160), 3.0)
    shifted[:, 77:85] = 2.0  # seen 2 cm to the side: the pole 1.5 px over, the wall 1 px
    shifted[:, 84] = 2.0
    rule = MaskRule(pose_error=PoseError.constant(0.02), stride_px=1, opening_px=0)
    frame, other = _frame(scene, rule=rule), _frame(shifted, rule=rule, k=1)
    pole = np.zeros((120, 160), bool)
    pole[10:110, 76:84] = True
    assert (frame.usable & pole).sum() > 200  # the pole's middle is no depth edge
    with_error = _grid(frame, pair_votes(CAMERA, frame, other, rule).violation)
    assert not with_error.any()
    farther = np.roll(shifted, 6, axis=1)  # missed by more than the pixel noise's window
    without = _frame(scene, rule=EXACT), _frame(farther, rule=EXACT, k=1)
    assert _grid(without[0], pair_votes(CAMERA, *without, EXACT).violation)[pole].any()


def test_one_violating_frame_is_not_enough() -> None:
    wall = np.full((120, 160), 3.0)
    moved = wall.copy()
    moved[40:80, 60:100] = 1.5  # frame k only
    holed = wall.copy()
    holed[40:80, 60:100] = 4.0  # one other frame measures farther there (a bad depth)
    frame = _frame(moved)
    mask = motion_mask(CAMERA, frame, [_frame(holed, k=1), _frame(moved, k=2)], EXACT)
    assert not (mask == MOVING).any()
    mask = motion_mask(CAMERA, frame, [_frame(holed, k=1), _frame(wall, k=2)], EXACT)
    assert (mask[45:75, 65:95] == MOVING).all()


@pytest.fixture(scope='module')
def synthetic(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_tum(tmp_path_factory.mktemp('tum') / 'source', SyntheticTum())


def test_the_synthetic_board_is_moving_and_the_wall_static(synthetic: Path) -> None:
    """The board slides along x in front of the wall, parallel to it: its depth does not
    change, so where it still covers its old place, only frames far enough apart see
    through it; with neighbours on both sides (images 15-21) that is all of it."""
    config = SyntheticTum()
    sequence = read_tum_rgbd(synthetic, intrinsics=config.intrinsics)
    rule = MaskRule(pose_error=PoseError.constant(0.002))
    frames = list(sequence_masks(sequence, rule))
    assert [f.image for f in frames] == list(range(3, config.images, 3))
    for frame in frames:
        board = board_mask(config, frame.stamp_ns)
        assert np.count_nonzero(frame.mask[~board] == MOVING) <= 0.001 * np.count_nonzero(~board)
        if 15 <= frame.image <= 21:
            assert np.mean(frame.mask[board] == MOVING) >= 0.9
        if board.any():  # its leading edge (beyond the depth edge), seen through before
            leading = board & np.roll(~board, -12, axis=1) & ~np.roll(~board, -4, axis=1)
            assert np.mean(frame.mask[leading] == MOVING) >= 0.9
    assert np.mean(frames[-1].mask[~board] == STATIC) >= 0.9


def test_bonn_crowd_static_opening_and_a_walking_person() -> None:
    source = dataset_or_skip('bonn_crowd', 'Bonn bonn_crowd')
    sequence = read_tum_rgbd(source, convention='bonn')
    rule = MaskRule(pose_error=PoseError((0.1, 0.2, 0.5), (0.004, 0.013, 0.023)))
    rays = pixel_rays(sequence.camera)

    def frame(image: int) -> DepthFrame:
        path = sequence.depth.files[sequence.depth_index[image]]
        depth = read_depth_m(path, sequence.depth_units_per_m)
        stamp = int(sequence.stamps_ns[image])
        return DepthFrame.build(rays, depth, sequence.poses[image], stamp, rule)

    def mask(image: int) -> np.ndarray:
        others = [frame(image + 3 * offset) for offset in rule.neighbours]
        return motion_mask(sequence.camera, frame(image), others, rule)

    opening = mask(90)  # no person before image 180
    assert np.mean(opening == MOVING) < 0.001
    assert np.mean(opening == STATIC) > 0.7
    walking = mask(699)  # a person walks to the right in the image's right third
    person = walking[100:460, 520:610]  # (by eye) torso and legs; they slide along themselves
    assert np.mean(person == MOVING) > 0.45
    assert np.mean(walking[30:400, 30:400] == MOVING) < 0.002  # desk, chair, robot, wall
    assert np.mean(walking == UNKNOWN) < 0.3
