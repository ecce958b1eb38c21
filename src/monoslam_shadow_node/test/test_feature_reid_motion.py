"""Re-identification under a camera turn that the predictions did not foresee: the tracks
carried into the image show its motion (``feature_reid.aligned_predictions``), and the
remembered tracks are searched where that motion puts them, in a region their spread
allows."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import monoslam_shadow_node.feature_tracker.core.feature_reid as feature_reid
import monoslam_shadow_node.feature_tracker.core.feature_tracker as feature_tracker
from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig
from monoslam_shadow_node.feature_tracker.core.feature_reid import (
    MOTION_MIN_TRACKS,
    aligned_predictions,
)
from monoslam_shadow_node.feature_tracker.core.feature_tracker import FeatureTracker
from monoslam_shadow_node.feature_tracker.core.feature_types import Predictions, TrackedFeatures

WIDTH, HEIGHT = 640, 480


def _affine(degrees: float, shift: tuple[float, float]) -> np.ndarray:
    """A turn about the image centre and a shift (2, 3)."""
    return cv2.getRotationMatrix2D((WIDTH / 2, HEIGHT / 2), degrees, 1.0) + np.array(
        [[0.0, 0.0, shift[0]], [0.0, 0.0, shift[1]]]
    )


def _apply(affine: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    return pixels @ affine[:, :2].T + affine[:, 2]


def _predictions(count: int, sigma_px: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pixels = np.column_stack(
        [rng.uniform(40, WIDTH - 40, count), rng.uniform(40, HEIGHT - 40, count)]
    )
    return pixels, np.broadcast_to(sigma_px**2 * np.eye(2), (count, 2, 2)).copy()


def test_remembered_predictions_follow_the_carried_tracks_motion() -> None:
    """30 carried tracks (5 of them on something that moved) tracked where a 2 degree turn
    and a (25, -18) px shift put them: each remembered track's prediction moves with that
    motion to within a pixel, its sigma falls from 30 px to the carried tracks' spread, and
    a remembered track with an uncertain depth of its own keeps that part."""
    motion = _affine(2.0, (25.0, -18.0))
    pixels, covariances = _predictions(36, 30.0, seed=1)
    covariances[35, 0, 0] += 20.0**2  # its own error, along u
    ids = np.arange(36, dtype=np.int64)
    rng = np.random.default_rng(2)
    tracked = _apply(motion, pixels[:30]) + rng.normal(0.0, 0.5, (30, 2))
    tracked[:5] += rng.uniform(15.0, 40.0, (5, 2))  # on a mover
    rows = {k: k for k in range(30)}
    out_pixels, out_covariances = aligned_predictions(
        pixels, covariances, ids, rows, tracked.astype(np.float32)
    )
    truth = _apply(motion, pixels[30:])
    assert np.max(np.linalg.norm(out_pixels[30:] - truth, axis=1)) < 1.0
    sigmas = np.sqrt(np.diagonal(out_covariances[30:35], axis1=1, axis2=2))
    assert np.all(sigmas < 2.0) and np.all(sigmas >= 1.0)  # never below a track's own noise
    assert 19.0 < np.sqrt(out_covariances[35, 0, 0]) < 21.0 and out_covariances[35, 1, 1] < 4.0
    np.testing.assert_array_equal(out_pixels[:30], pixels[:30])  # carried: as predicted


@pytest.mark.parametrize('carried', [MOTION_MIN_TRACKS - 1, 0])
def test_too_few_carried_tracks_leave_the_predictions_as_they_are(carried: int) -> None:
    pixels, covariances = _predictions(carried + 3, 30.0, seed=3)
    ids = np.arange(len(pixels), dtype=np.int64)
    tracked = (pixels[:carried] + 20.0).astype(np.float32)
    out = aligned_predictions(pixels, covariances, ids, {k: k for k in range(carried)}, tracked)
    np.testing.assert_array_equal(out[0], pixels)
    np.testing.assert_array_equal(out[1], covariances)


def test_a_prediction_not_in_view_is_not_moved() -> None:
    """A zero covariance means no search is due (SLAM's 'not in view'): it stays so."""
    pixels, covariances = _predictions(20, 30.0, seed=4)
    covariances[19] = 0.0
    ids = np.arange(20, dtype=np.int64)
    tracked = (pixels[:15] + 10.0).astype(np.float32)
    out = aligned_predictions(pixels, covariances, ids, {k: k for k in range(15)}, tracked)
    np.testing.assert_array_equal(out[0][19], pixels[19])
    np.testing.assert_array_equal(out[1][19], np.zeros((2, 2)))
    np.testing.assert_allclose(out[0][15:19], pixels[15:19] + 10.0, atol=1e-6)


def _texture(seed: int) -> np.ndarray:
    noise = np.random.default_rng(seed).uniform(0.0, 255.0, (HEIGHT, WIDTH)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), 2.0)
    return np.clip((smooth - smooth.mean()) / smooth.std() * 45.0 + 128.0, 0, 255).astype(np.uint8)


def _turn(
    monkeypatch: pytest.MonkeyPatch, aligned: bool
) -> tuple[TrackedFeatures, dict[int, np.ndarray]]:
    """View A; then A with its left third covered (those tracks are dropped and remembered);
    then A uncovered and shifted by (30, 12) px, with predictions at A's pixels and a 30 px
    sigma, as a camera's prediction made before a turn it did not foresee. Return the last
    image's features and where the covered tracks are in it, by id."""
    if not aligned:
        monkeypatch.setattr(feature_tracker, 'aligned_predictions', lambda p, c, *_: (p, c))
    source = _texture(5)
    tracker = FeatureTracker(TrackerConfig(max_features=150, detect_every_n_frames=100))
    first = tracker.track(source)
    covered = source.copy()
    covered[:, : WIDTH // 3] = 128
    tracker.track(covered)
    hidden = {
        int(i): p + np.array([30.0, 12.0])
        for i, p in zip(first.ids, first.pixels, strict=True)
        if p[0] < WIDTH // 3 - 15
    }
    shift = np.float32([[1, 0, 30], [0, 1, 12]])
    back = cv2.warpAffine(source, shift, (WIDTH, HEIGHT), borderMode=cv2.BORDER_REFLECT)
    covariances = np.broadcast_to(900.0 * np.eye(2), (len(first.ids), 2, 2))
    result = tracker.track(back, Predictions(first.ids, first.pixels, covariances))
    return result, hidden


def test_tracks_behind_an_occluder_come_back_after_an_unforeseen_turn(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With the carried tracks' motion most covered tracks come back under their ids, each
    within a pixel of where the turn put it; without it, their 90 px regions are too wide to
    search and none does."""
    result, hidden = _turn(monkeypatch, aligned=True)
    found = {int(i): p for i, p in zip(result.ids, result.pixels, strict=True) if int(i) in hidden}
    assert len(hidden) >= 20 and len(found) >= 0.8 * len(hidden)
    assert result.counts.revived >= len(found)
    assert max(np.linalg.norm(found[i] - hidden[i]) for i in found) < 1.0
    with monkeypatch.context() as patch:
        plain, _ = _turn(patch, aligned=False)
    assert plain.counts.revived == 0 and plain.counts.unsearched >= 0.8 * len(hidden)


@pytest.mark.parametrize('budget', [None, 2])
def test_alignments_per_image_are_bounded_in_the_predictions_order(
    monkeypatch: pytest.MonkeyPatch, budget: int | None
) -> None:
    """20 remembered tracks whose templates match nowhere as they are: every candidate would
    need an alignment, and only the first ``reid_max_alignments`` are made (the default, and
    2), for the first predictions; all 20 still count as searched, and the candidates left
    are counted."""
    calls: list[tuple[int, int]] = []

    def counted(gray: np.ndarray, core: np.ndarray, x: int, y: int) -> None:
        calls.append((x, y))

    monkeypatch.setattr(feature_reid, 'refine_match', counted)
    gray = _texture(7)
    other = _texture(8)
    config = TrackerConfig() if budget is None else TrackerConfig(reid_max_alignments=budget)
    side = config.lk_window_px + 2 * feature_reid.TEMPLATE_MARGIN_PX
    pixels, covariances = _predictions(20, 5.0, seed=9)
    templates = {}
    for k, (u, v) in enumerate(pixels):
        patch = cv2.getRectSubPix(other, (side, side), (float(u), float(v)))
        templates[k] = np.asarray(patch, np.uint8)
    ids = np.arange(20, dtype=np.int64)
    warps = np.zeros((20, 2, 2))
    empty = np.zeros((0, 2)), np.zeros((0, 2))
    found, search = feature_reid.search_predicted(
        config, gray, templates, (ids, pixels, covariances, warps), empty
    )
    assert not found and search.searched == 20
    assert len(calls) == config.reid_max_alignments
    assert search.unaligned >= 20 - config.reid_max_alignments  # counted, not silent
    first = pixels[0]
    assert np.hypot(calls[0][0] - first[0], calls[0][1] - first[1]) <= 3 * 5.0 + 1


def test_a_prediction_that_can_be_searched_is_moved_but_keeps_its_covariance() -> None:
    """Narrowed only where too wide to search: with the tracker's 80 px (3-sigma half-axis),
    a remembered track predicted with a 20 px sigma (a returning map feature whose error is
    the old map's drift, not the image's motion) moves with the carried tracks and keeps its
    20 px; one with 30 px is narrowed to their spread as before."""
    motion = _affine(2.0, (25.0, -18.0))
    pixels, covariances = _predictions(32, 30.0, seed=5)
    covariances[31] = 20.0**2 * np.eye(2)
    ids = np.arange(32, dtype=np.int64)
    tracked = _apply(motion, pixels[:30]) + np.random.default_rng(6).normal(0.0, 0.5, (30, 2))
    rows = {k: k for k in range(30)}
    out_pixels, out_covariances = aligned_predictions(
        pixels, covariances, ids, rows, tracked.astype(np.float32), 80.0
    )
    truth = _apply(motion, pixels[30:])
    assert np.max(np.linalg.norm(out_pixels[30:] - truth, axis=1)) < 1.0
    np.testing.assert_array_equal(out_covariances[31], covariances[31])
    assert np.all(np.sqrt(np.diagonal(out_covariances[30])) < 2.0)
