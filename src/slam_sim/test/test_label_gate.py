"""The labelled-static gate of variant (a) (slam_sim.core.label_gate) and its masks file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam_core.camera import CameraModel
from slam_sim.core.depth_labels import MOVING, STATIC, UNKNOWN, PoseError
from slam_sim.core.label_gate import LabelGate, LabelMasks, read_label_masks, write_label_masks
from slam_sim.core.mask_labels import pixel_codes, sighting_codes
from slam_sim.core.motion_masks import MaskedFrame

STAMPS = np.array([100, 200, 300], dtype=np.int64) * 1_000_000
CAMERA = CameraModel(60, 40, np.array([[50.0, 0, 30], [0, 50.0, 20], [0, 0, 1]]), np.zeros(5))


def _codes(depth_m: float = 0.0) -> LabelMasks:
    """Three 40 x 60 images from a camera at rest: the left half STATIC, the right half
    MOVING, the bottom rows UNKNOWN; in the second image the right half is STATIC too. The
    depth maps hold ``depth_m`` everywhere (0: none)."""
    codes = np.full((3, 40, 60), STATIC, dtype=np.int8)
    codes[:, :, 30:] = MOVING
    codes[1, :, 30:] = STATIC
    codes[:, 30:, :] = UNKNOWN
    depth = np.full((3, 40, 60), round(1000 * depth_m), dtype=np.uint16)
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    return LabelMasks(STAMPS, codes, depth, poses, CAMERA, PoseError.constant(0.001))


def test_a_track_passes_once_labelled_static_and_never_after_it_was_seen_moving() -> None:
    """Track 1 sits on the static half, 2 on the moving half, 3 on unknown pixels; 4 moves
    from the moving to the static half. A frame between codes changes no label; a track once
    on MOVING pixels stays withheld."""
    gate = LabelGate(_codes())
    ids = np.array([1, 2, 3, 4])
    first = gate.admit(int(STAMPS[0]), ids, np.array([[5, 5], [45, 5], [5, 35], [40, 10]]))
    assert first.tolist() == [True, False, False, False]
    between = gate.admit(int(STAMPS[0]) + 50_000_000, ids, np.array([[5, 5]] * 4))
    assert between.tolist() == [True, False, False, False]
    second = gate.admit(int(STAMPS[1]), ids, np.array([[5, 5], [45, 5], [5, 35], [10, 10]]))
    # tracks 2 and 4 are on STATIC pixels now, but were MOVING before: withheld for good
    assert second.tolist() == [True, False, False, False]
    late = np.array([5, 6])  # new tracks: 5 on the static half, 6 on the moving half
    third = gate.admit(int(STAMPS[2]), late, np.array([[5, 5], [45, 5]]))
    assert third.tolist() == [True, False]
    assert (gate.frames, gate.frames_with_masks, gate.features) == (4, 3, 14)
    assert gate.passed == 1 + 1 + 1 + 1
    assert gate.tracks_moving() == 3  # tracks 2, 4 and 6 (3 has no decided code)


def test_renumbered_ids_and_finer_stamps_give_the_same_decisions() -> None:
    """The same sightings under other track ids, stamped a fraction of a millisecond off
    (within the tolerance), pass the same tracks."""
    pixels = [np.array([[5, 5], [45, 5], [40, 10]]), np.array([[5, 5], [45, 5], [10, 10]])]
    plain, renumbered = LabelGate(_codes()), LabelGate(_codes())
    for n, frame in enumerate(pixels):
        a = plain.admit(int(STAMPS[n]), np.array([1, 2, 4]), frame)
        b = renumbered.admit(int(STAMPS[n]) + 437, np.array([7001, 9, 7 * 4 + 1000]), frame)
        assert a.tolist() == b.tolist()


def test_a_track_that_moves_on_static_pixels_is_withheld_by_its_own_motion() -> None:
    """On STATIC pixels with a depth (2 m, a camera at rest), a track whose pixel stays put
    passes; one that slides 8 px per mask (a torso moving along itself) is withheld once two
    successive motions agree (at the third mask), and a single 8 px jump is not enough."""
    masks = _codes(depth_m=2.0)
    masks.codes[:, :30, :] = STATIC
    gate = LabelGate(masks)
    ids = np.array([1, 2, 3])
    paths = [[[5, 5], [5, 5], [5, 5]], [[5, 5], [13, 5], [21, 5]], [[5, 5], [13, 5], [13, 5]]]
    decisions = [
        gate.admit(int(stamp), ids, np.array([path[n] for path in paths], dtype=float)).tolist()
        for n, stamp in enumerate(STAMPS)
    ]
    assert decisions == [[True, True, True], [True, True, True], [True, False, True]]


def test_label_masks_round_trip_and_a_bad_file_is_named(tmp_path: Path) -> None:
    path = tmp_path / 'label_masks.npz'
    path.write_bytes(write_label_masks(_codes(depth_m=1.5)))
    read = read_label_masks(path)
    assert np.array_equal(read.stamps_ns, STAMPS)
    assert np.array_equal(read.codes, _codes().codes)
    assert np.array_equal(read.camera.K, CAMERA.K) and read.camera.width == 60
    assert read.pose_error.at(3.0) == 0.001
    assert np.allclose(read.frame(1).depth_m, 1.5) and read.frame(1).stamp_ns == STAMPS[1]
    assert np.all(np.isnan(_codes().frame(0).depth_m))
    bad = tmp_path / 'bad.npz'
    bad.write_bytes(b'not a zip file')
    with pytest.raises(ValueError, match=r'bad\.npz: not a label masks file'):
        read_label_masks(bad)
    masks = _codes()
    with pytest.raises(ValueError, match='stamps must increase'):
        LabelMasks(STAMPS[::-1].copy(), masks.codes, masks.depth_mm, masks.poses, CAMERA,
                   masks.pose_error)  # fmt: skip
    with pytest.raises(ValueError, match='tolerance_ns'):
        LabelGate(masks, tolerance_ns=-1)


def test_pixel_codes_take_the_nearer_surface_where_the_mask_is_unknown() -> None:
    """An UNKNOWN pixel (a depth edge, where trackers put corners) takes the code of the
    nearer of the moving and the static surface within the radius (4 px), as a sighting
    does; one with neither within the radius stays UNKNOWN."""
    mask = np.full((20, 40), UNKNOWN, dtype=np.int8)
    mask[:, :10], mask[:, 14:20] = STATIC, MOVING
    for moving_depth, between in ((1.0, MOVING), (5.0, STATIC)):
        depth = np.full((20, 40), 3.0)
        depth[:, 14:20] = moving_depth
        frame = MaskedFrame(0, 0, np.eye(4), depth, mask)
        codes = pixel_codes(frame, 4)
        assert codes[5, 11] == between
        assert codes[5, 3] == STATIC and codes[5, 16] == MOVING and codes[5, 30] == UNKNOWN
        assert sighting_codes(frame, np.array([[11.2, 4.8], [-3.0, 5.0]]), 4).tolist() == [
            between,
            UNKNOWN,
        ]
