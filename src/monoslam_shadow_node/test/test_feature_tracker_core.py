"""The feature tracker's core on real images through OpenCV: a seeded random texture warped
by known homographies, so that where every tracked point should be is known exactly."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig
from monoslam_shadow_node.feature_tracker.core.feature_detection import SUBPIXEL_HALF_WINDOW_PX
from monoslam_shadow_node.feature_tracker.core.feature_tracker import FeatureTracker
from monoslam_shadow_node.feature_tracker.core.feature_types import (
    DROP_REASONS,
    Predictions,
    TrackedFeatures,
)

WIDTH, HEIGHT = 640, 480
ACCURACY_PX = 0.3


def texture(height: int, width: int, seed: int, sigma_px: float = 2.0) -> np.ndarray:
    """A smooth random texture (float32 gray levels around 128, std 45)."""
    noise = np.random.default_rng(seed).uniform(0.0, 255.0, (height, width)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), sigma_px)
    return np.clip((smooth - smooth.mean()) / smooth.std() * 45.0 + 128.0, 0.0, 255.0)


def to_gray(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def warped(source: np.ndarray, homography: np.ndarray) -> np.ndarray:
    """The (HEIGHT, WIDTH) uint8 image of ``source`` moved by ``homography`` (source pixel
    -> image pixel; OpenCV's pixel-centre convention on both sides)."""
    image = cv2.warpPerspective(
        source, homography, (WIDTH, HEIGHT), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
    )
    return to_gray(image)


def moved(homography: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Apply a homography to pixels (N, 2)."""
    points = np.column_stack([pixels, np.ones(len(pixels))]) @ homography.T
    return points[:, :2] / points[:, 2:]


def shifted(du: float, dv: float, base: np.ndarray | None = None) -> np.ndarray:
    """``base`` (default: identity) followed by a translation of (du, dv) px."""
    shift = np.array([[1.0, 0.0, du], [0.0, 1.0, dv], [0.0, 0.0, 1.0]])
    return shift @ (np.eye(3) if base is None else base)


def camera_motion(k: int) -> np.ndarray:
    """Frame k of a slow camera motion: translation, rotation, zoom and a little perspective."""
    angle, scale = 0.003 * k, 1.0 + 0.004 * k
    cos, sin = scale * np.cos(angle), scale * np.sin(angle)
    return np.array([[cos, -sin, 1.7 * k], [sin, cos, -0.9 * k], [2e-6 * k, 1e-6 * k, 1.0]])


def cell_counts(pixels: np.ndarray, rows: int = 4, cols: int = 4) -> np.ndarray:
    """Features per cell of a rows x cols grid over the image (rows, cols)."""
    col = np.clip((pixels[:, 0] * cols / WIDTH).astype(int), 0, cols - 1)
    row = np.clip((pixels[:, 1] * rows / HEIGHT).astype(int), 0, rows - 1)
    return np.bincount(row * cols + col, minlength=rows * cols).reshape(rows, cols)


def by_id(result: TrackedFeatures) -> dict[int, np.ndarray]:
    return dict(zip(result.ids.tolist(), result.pixels, strict=True))


def check_output(result: TrackedFeatures, config: TrackerConfig) -> None:
    """What every result must satisfy: shapes and types, finite pixels inside the margin,
    ascending unique ids from 1, counts that add up."""
    count = len(result.ids)
    assert result.ids.dtype == np.int64 and result.pixels.dtype == np.float64
    assert result.pixels.shape == (count, 2) and result.ages.shape == (count,)
    assert np.all(np.isfinite(result.pixels))
    assert np.all(np.diff(result.ids) > 0) and (count == 0 or result.ids[0] >= 1)
    assert count <= config.max_features
    margin = config.border_margin_px
    assert np.all(result.pixels >= margin - 1e-3)
    assert np.all(result.pixels[:, 0] <= WIDTH - 1 - margin + 1e-3)
    assert np.all(result.pixels[:, 1] <= HEIGHT - 1 - margin + 1e-3)
    assert result.counts.tracked + result.counts.revived + result.counts.new == count
    assert int(np.sum(result.ages == 1)) == result.counts.new


@pytest.fixture(scope='module')
def scene() -> np.ndarray:
    return texture(HEIGHT, WIDTH, seed=0)


@pytest.mark.parametrize('detector', ['shi_tomasi', 'fast'])
def test_tracks_follow_the_known_motion_within_a_third_of_a_pixel(
    scene: np.ndarray, detector: str
) -> None:
    config = TrackerConfig(detector=detector)
    tracker = FeatureTracker(config)
    origin: dict[int, np.ndarray] = {}  # id -> where in the texture it was first seen
    errors = []
    first_ids: set[int] = set()
    for k in range(10):
        motion = camera_motion(k)
        result = tracker.track(warped(scene, motion), None)
        check_output(result, config)
        if k == 0:
            first_ids = set(result.ids.tolist())
            assert len(first_ids) == config.max_features
        inverse = np.linalg.inv(motion)
        for track_id, pixel in by_id(result).items():
            if track_id in origin:
                errors.append(np.linalg.norm(moved(motion, origin[track_id][None])[0] - pixel))
            else:
                origin[track_id] = moved(inverse, pixel[None])[0]
    assert len(errors) > 1000
    assert max(errors) < ACCURACY_PX
    survivors = first_ids & set(result.ids.tolist())
    assert len(survivors) >= 0.85 * len(first_ids)  # some leave the image: it moves 15 px


def test_ids_start_at_one_persist_and_are_never_reused(scene: np.ndarray) -> None:
    tracker = FeatureTracker(TrackerConfig(max_features=50))
    first = tracker.track(warped(scene, np.eye(3)))
    assert first.ids.tolist() == list(range(1, 51))
    second = tracker.track(warped(scene, shifted(0.5, 0.25)))
    assert set(second.ids.tolist()) == set(first.ids.tolist())
    assert second.counts.tracked == 50 and second.counts.new == 0
    assert np.all(second.ages == 2)

    assert tracker.reset() == 50
    after_reset = tracker.track(warped(scene, shifted(0.5, 0.25)))
    assert after_reset.counts.reset == 50 and after_reset.counts.tracked == 0
    assert after_reset.ids.min() == 51 and np.all(after_reset.ages == 1)

    smaller = to_gray(scene[:240, :320])  # another image size: a restart too
    resized = tracker.track(smaller)
    assert resized.counts.reset == len(after_reset.ids)
    assert resized.ids.min() > after_reset.ids.max()
    assert tracker.next_id == resized.ids.max() + 1


def test_forward_backward_check_drops_a_point_whose_look_alike_disappears() -> None:
    """Frame 0 holds a copy of a corner's neighbourhood 20 px to its right; in frame 1 (the
    scene shifted by (-2, -1) px) the copy is gone. LK still finds an end for the copy's
    track (status 1), 7 px off; tracked back from there it lands 10 px from where it
    started: the forward-backward check drops it (the patch error check alone would too)."""
    source = texture(960, 1280, seed=1)
    base = shifted(-300.0, -200.0)
    plain, after = warped(source, base), warped(source, shifted(-2.0, -1.0, base))
    corner = np.rint(FeatureTracker().track(plain).pixels[0]).astype(int)  # the strongest
    u, v, half, offset = corner[0], corner[1], 12, 20
    with_copy = plain.copy()
    with_copy[v - half : v + half + 1, u + offset - half : u + offset + half + 1] = plain[
        v - half : v + half + 1, u - half : u + half + 1
    ]

    def track_copy(config: TrackerConfig) -> tuple[bool, bool, TrackedFeatures]:
        tracker = FeatureTracker(config)
        first = tracker.track(with_copy)
        distances = np.linalg.norm(first.pixels - (corner + np.array([offset, 0])), axis=1)
        assert distances.min() < 1.0, 'the copy should be detected'
        copy_id = int(first.ids[np.argmin(distances)])
        original_id = int(first.ids[np.argmin(np.linalg.norm(first.pixels - corner, axis=1))])
        result = tracker.track(after)
        return copy_id in result.ids, original_id in result.ids, result

    copy_kept, original_kept, result = track_copy(TrackerConfig(max_lk_error=0.0))
    assert not copy_kept and original_kept
    assert result.counts.forward_backward >= 1 and result.counts.lost == 0
    nothing = TrackerConfig(max_lk_error=0.0, fb_threshold_px=0.0, max_drift_px=0.0)
    copy_kept, original_kept, _ = track_copy(nothing)
    assert copy_kept and original_kept  # nothing else stops it
    copy_kept, original_kept, result = track_copy(dataclasses.replace(nothing, max_drift_px=2.0))
    assert not copy_kept and original_kept  # its template (the copy) is not where it went
    assert result.counts.drift >= 1
    copy_kept, original_kept, _ = track_copy(TrackerConfig())
    assert not copy_kept and original_kept


def occluder_frames(count: int, edge_px: float, speed_px: float) -> list[np.ndarray]:
    """A static background and, over its right part (u >= the edge), a nearer surface with
    its own texture that moves left by ``speed_px`` per frame, covering the background."""
    background = texture(HEIGHT, WIDTH, seed=3)
    near = texture(HEIGHT, WIDTH, seed=4, sigma_px=6.0)
    columns = np.arange(WIDTH, dtype=np.float32)[None, :]
    frames = []
    for k in range(count):
        shift = np.float32([[1.0, 0.0, -speed_px * k], [0.0, 1.0, 0.0]])
        moved_near = cv2.warpAffine(
            near, shift, (WIDTH, HEIGHT), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
        )
        cover = np.clip(columns - (edge_px - speed_px * k) + 0.5, 0.0, 1.0)
        frames.append(to_gray(background * (1.0 - cover) + moved_near * cover))
    return frames


def test_drift_check_stops_tracks_dragged_by_an_occluding_edge() -> None:
    """Background corners just left of an advancing occluder's edge (0.5 px per frame): each
    LK step is small and passes the other checks, so without the drift check the tracks are
    dragged along by the edge (measured: up to ~20 px in 60 frames); with it they are
    dropped once they leave their template (measured: within ~5 px)."""
    frames = occluder_frames(60, edge_px=400.0, speed_px=0.5)

    def dragged(config: TrackerConfig) -> tuple[float, int]:
        tracker = FeatureTracker(config)
        first = tracker.track(frames[0])
        near = (first.pixels[:, 0] > 385.0) & (first.pixels[:, 0] < 400.0)
        start = {int(i): p for i, p in zip(first.ids[near], first.pixels[near], strict=True)}
        worst, drops = 0.0, 0
        for image in frames[1:]:
            result = tracker.track(image)
            drops += result.counts.drift
            for track_id, pixel in zip(result.ids.tolist(), result.pixels, strict=True):
                if track_id in start:
                    worst = max(worst, float(np.linalg.norm(pixel - start[track_id])))
        assert len(start) >= 5, 'corners next to the edge should be detected'
        return worst, drops

    unchecked, _ = dragged(TrackerConfig(max_drift_px=0.0))
    checked, drops = dragged(TrackerConfig())
    assert unchecked > 10.0
    assert checked < 8.0 and drops >= 5


def test_occluded_points_are_dropped(scene: np.ndarray) -> None:
    """A 161 px square of other texture covers part of the scene in frame 1: no track under
    it survives (the patch error and forward-backward checks), the others all do."""
    tracker = FeatureTracker()
    first = tracker.track(warped(scene, np.eye(3)))
    image = warped(scene, shifted(2.0, 1.0))
    centre, half = np.array([320, 240]), 80
    image[centre[1] - half : centre[1] + half + 1, centre[0] - half : centre[0] + half + 1] = (
        to_gray(texture(2 * half + 1, 2 * half + 1, seed=9))
    )
    result = tracker.track(image)
    where = first.pixels + np.array([2.0, 1.0])
    covered = np.all(np.abs(where - centre) <= half - 10, axis=1)  # whole LK patch covered
    clear = np.any(np.abs(where - centre) >= half + 12, axis=1)
    assert covered.sum() >= 3
    kept = set(result.ids.tolist())
    assert not kept & set(first.ids[covered].tolist())
    assert set(first.ids[clear].tolist()) <= kept


def test_new_features_cover_every_cell_of_a_uniform_texture(scene: np.ndarray) -> None:
    config = TrackerConfig()
    result = FeatureTracker(config).track(warped(scene, np.eye(3)))
    counts = cell_counts(result.pixels)
    assert len(result.ids) == 150
    assert counts.min() >= 5  # cells take up to config.cell_quota = 10 first


def test_the_grid_spreads_features_where_texture_is_weak() -> None:
    """Contrast fades from 1 at the left edge to 0.1 at the right: without the grid nearly
    all corners go left; with it every cell gets its share."""
    gain = np.linspace(1.0, 0.1, WIDTH)[None, :]
    image = to_gray((texture(HEIGHT, WIDTH, seed=3) - 128.0) * gain + 128.0)
    spread = cell_counts(FeatureTracker().track(image).pixels)
    assert spread.min() >= 5
    one_cell = cell_counts(
        FeatureTracker(TrackerConfig(grid_rows=1, grid_cols=1)).track(image).pixels
    )
    assert one_cell[:, 2:].sum() < 10  # the right half: what the grid is for


def test_detection_fills_only_where_tracks_were_lost(scene: np.ndarray) -> None:
    """A cell-sized patch changes to other texture in frame 1 (an object passes): its tracks
    die, and the new features of that frame start there; the other tracks go on."""
    tracker = FeatureTracker(TrackerConfig(detect_every_n_frames=1))
    first = tracker.track(warped(scene, np.eye(3)))
    changed = warped(scene, shifted(1.0, 0.5))
    changed[120:240, 160:320] = to_gray(texture(120, 160, seed=5))  # cell (1, 1) of 4x4
    second = tracker.track(changed)
    where = first.pixels + np.array([1.0, 0.5])
    inside = np.all((where >= [172, 132]) & (where < [308, 228]), axis=1)  # whole LK patch
    outside = np.any((where < [150, 110]) | (where >= [330, 250]), axis=1)
    assert inside.sum() >= 3
    assert not set(first.ids[inside].tolist()) & set(second.ids.tolist())
    assert set(first.ids[outside].tolist()) <= set(second.ids.tolist())
    new = second.pixels[second.ages == 1]
    assert second.counts.new >= inside.sum()
    assert np.all((new >= [160 - 12, 120 - 12]) & (new < [320 + 12, 240 + 12]))  # and its edges


def test_cells_without_texture_leave_their_share_to_the_others() -> None:
    """The left half is flat: all max_features features go to the right half."""
    image = to_gray(texture(HEIGHT, WIDTH, seed=4))
    image[:, : WIDTH // 2] = 90
    result = FeatureTracker().track(image)
    assert len(result.ids) == 150 and np.all(result.pixels[:, 0] > WIDTH // 2 - 10)


@pytest.mark.parametrize('detector', ['shi_tomasi', 'fast'])
@pytest.mark.parametrize('subpixel', [False, True])
def test_max_features_and_min_distance_hold_over_a_sequence(
    scene: np.ndarray, detector: str, subpixel: bool
) -> None:
    config = TrackerConfig(
        max_features=40,
        detector=detector,
        min_distance_px=15.0,
        subpixel_refinement=subpixel,
        detect_every_n_frames=1,
    )
    # Detection keeps min_distance_px between pixels (existing tracks rounded); refinement
    # then moves a new corner by at most SUBPIXEL_HALF_WINDOW_PX.
    least = config.min_distance_px - 1.0 - (SUBPIXEL_HALF_WINDOW_PX if subpixel else 0.0)
    tracker = FeatureTracker(config)
    for k in range(6):
        result = tracker.track(warped(scene, camera_motion(3 * k)))
        check_output(result, config)
        assert len(result.ids) == 40
        new = result.pixels[result.ages == 1]
        if len(new):
            gaps = np.linalg.norm(new[:, None, :] - result.pixels[None, :, :], axis=2)
            gaps[gaps == 0.0] = np.inf  # each new feature itself
            assert gaps.min() >= least


def test_crowded_tracks_keep_the_older_one(scene: np.ndarray) -> None:
    """Zooming out draws the features together: a track that comes within half of
    min_distance_px of an older one is dropped. (8 % zoom per image is beyond the drift
    check's translation-only templates, which would drop the tracks first: it is off here.)"""
    config = TrackerConfig(min_distance_px=20.0, max_drift_px=0.0)
    tracker = FeatureTracker(config)
    crowded = 0
    centre = shifted(320.0, 240.0)
    for k in range(8):
        zoom = np.diag([0.92**k, 0.92**k, 1.0])
        result = tracker.track(warped(scene, centre @ zoom @ np.linalg.inv(centre)))
        crowded += result.counts.crowded
        gaps = np.linalg.norm(result.pixels[:, None, :] - result.pixels[None, :, :], axis=2)
        np.fill_diagonal(gaps, np.inf)
        assert gaps.min() >= 0.5 * config.min_distance_px
    assert crowded > 0


def test_predictions_catch_a_jump_that_plain_lk_misses() -> None:
    """A 60 px jump is beyond two pyramid levels: plain LK loses every track. Started from
    predictions 0.7 px off, the tracks land within a third of a pixel, and those predicted
    outside the image are dropped."""
    source = texture(960, 1280, seed=2)
    base = shifted(-300.0, -200.0)
    jump = shifted(60.0, 20.0, base)
    config = TrackerConfig(lk_pyramid_levels=2)

    def run(predict: bool) -> tuple[int, int, TrackedFeatures]:
        tracker = FeatureTracker(config)
        first = tracker.track(warped(source, base))
        truth = moved(jump @ np.linalg.inv(base), first.pixels)
        noise = np.random.default_rng(0).normal(0.0, 0.7, truth.shape)
        predictions = Predictions(first.ids, truth + noise) if predict else None
        result = tracker.track(warped(source, jump), predictions)
        check_output(result, config)
        found = by_id(result)
        errors = [
            np.linalg.norm(found[i] - t)
            for i, t in zip(first.ids.tolist(), truth, strict=True)
            if i in found
        ]
        good = sum(e < ACCURACY_PX for e in errors)
        return good, len(errors) - good, result

    good, bad, plain = run(predict=False)
    assert good == 0 and bad <= 3 and plain.counts.predicted == 0
    good, bad, predicted = run(predict=True)
    assert good >= 100 and bad == 0
    assert predicted.counts.predicted == good and predicted.counts.border >= 5


def test_unusable_predictions_are_ignored_and_leaving_ones_drop_the_track(
    scene: np.ndarray,
) -> None:
    tracker = FeatureTracker(TrackerConfig(max_features=30))
    first = tracker.track(warped(scene, np.eye(3)))
    ids = np.array([first.ids[0], first.ids[1], first.ids[2], 10**12])
    pixels = np.array([[np.nan, 5.0], [-3.0, 10.0], [WIDTH + 5.0, 10.0], [100.0, 100.0]])
    result = tracker.track(warped(scene, shifted(1.0, 1.0)), Predictions(ids, pixels))
    assert result.counts.predicted == 0 and result.counts.tracked == 28
    assert result.counts.border == 2 and first.ids[0] in result.ids  # NaN: ignored
    assert not {int(first.ids[1]), int(first.ids[2])} & set(result.ids.tolist())
    with pytest.raises(ValueError, match='2 ids but 1 pixels'):
        tracker.track(warped(scene, shifted(2.0, 2.0)), Predictions(ids[:2], pixels[:1]))


@pytest.mark.parametrize(
    ('image', 'message'),
    [
        (np.zeros((0, 0), np.uint8), r'empty image \(0x0 px\)'),
        (np.zeros((480, 640, 3), np.uint8), '2-D uint8 .* got 3-D uint8'),
        (np.zeros((480, 640), np.float32), 'got 2-D float32'),
        ([[1, 2], [3, 4]], 'got <class .list.>'),
    ],
)
def test_images_the_tracker_cannot_use_are_refused_and_change_nothing(
    scene: np.ndarray, image: object, message: str
) -> None:
    tracker = FeatureTracker()
    first = tracker.track(warped(scene, np.eye(3)))
    with pytest.raises(ValueError, match=message):
        tracker.track(image)
    after = tracker.track(warped(scene, shifted(0.5, 0.5)))
    assert after.counts.tracked == len(first.ids) and after.counts.reset == 0


def test_a_flat_image_gives_no_features_and_no_nan() -> None:
    tracker = FeatureTracker()
    flat = np.full((HEIGHT, WIDTH), 77, np.uint8)
    for _ in range(2):
        result = tracker.track(flat)
        assert len(result.ids) == 0 and result.pixels.shape == (0, 2)


def test_counts_name_every_drop_reason() -> None:
    counts = dataclasses.fields(
        FeatureTracker().track(np.full((8, 8), 1, np.uint8)).counts.__class__
    )
    assert set(DROP_REASONS) <= {field.name for field in counts}


@pytest.mark.parametrize(
    ('field', 'value', 'message'),
    [
        ('max_features', 0, r'max_features=0: must be >= 1'),
        ('max_features', 2.5, r'max_features=2\.5: must be an integer'),
        ('detector', 'orb', r"detector='orb': must be one of"),
        ('quality_level', 1.0, r'quality_level=1\.0: must be in \(0, 1\)'),
        ('min_distance_px', 0.5, r'min_distance_px=0\.5: must be >= 1'),
        ('lk_window_px', 3, r'lk_window_px=3: must be in \[5, 101\]'),
        ('fb_threshold_px', -1.0, r'fb_threshold_px=-1\.0: must be >= 0'),
        ('fb_threshold_px', float('inf'), r'fb_threshold_px=inf: must be a finite number'),
        ('subpixel_refinement', 1, r'subpixel_refinement=1: must be true or false'),
        ('grid_rows', True, r'grid_rows=True: must be an integer'),
    ],
)
def test_invalid_settings_name_the_field(field: str, value: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        TrackerConfig(**{field: value})  # type: ignore[arg-type]


def _away_and_back(
    config: TrackerConfig, back: np.ndarray
) -> tuple[FeatureTracker, TrackedFeatures, np.ndarray]:
    """View A, then an unrelated view (every track dropped, new ones started there), then
    ``back`` (view A moved by a homography). Return the tracker (before tracking ``back``),
    view A's features and where they are in ``back``."""
    source = texture(HEIGHT, WIDTH, seed=5)
    tracker = FeatureTracker(dataclasses.replace(config, detect_every_n_frames=1))
    first = tracker.track(warped(source, np.eye(3)))
    away = tracker.track(warped(texture(HEIGHT, WIDTH, seed=6), np.eye(3)))
    assert away.counts.tracked <= 3 and away.counts.new >= 50  # A's tracks are all but gone
    return tracker, first, moved(back, first.pixels)


def test_a_dropped_track_is_re_identified_where_its_prediction_expects_it() -> None:
    """The camera turns away and back: predictions with a 4 px sigma (as SLAM's 3-sigma
    search region) bring view A's tracks back with their own ids, within half a pixel; the
    tracks started in between are not duplicated on them."""
    config = TrackerConfig(max_features=120, detect_every_n_frames=1)
    back = shifted(3.0, -2.0)
    tracker, first, truth = _away_and_back(config, back)
    rng = np.random.default_rng(1)
    covariance = np.broadcast_to(16.0 * np.eye(2), (len(first.ids), 2, 2))
    guess = truth + rng.normal(0.0, 2.0, truth.shape)
    source = texture(HEIGHT, WIDTH, seed=5)
    result = tracker.track(warped(source, back), Predictions(first.ids, guess, covariance))
    check_output(result, config)
    found = by_id(result)
    errors = [np.linalg.norm(found[i] - t) for i, t in zip(first.ids.tolist(), truth, strict=True)
              if i in found]  # fmt: skip
    assert result.counts.searched >= 0.9 * len(first.ids)
    assert result.counts.revived == len(errors) >= 0.9 * len(first.ids)
    assert max(errors) < 0.5
    # the next image tracks them on, and nothing sits on a revived track
    after = tracker.track(warped(source, shifted(1.0, 1.0, back)))
    check_output(after, config)
    assert set(first.ids.tolist()) & set(after.ids.tolist()) >= set(found) & set(
        first.ids.tolist()
    ) - {i for i in found if i not in after.ids}
    pixels = after.pixels
    gaps = np.linalg.norm(pixels[:, None] - pixels[None], axis=2) + 1e9 * np.eye(len(pixels))
    assert np.min(gaps) >= 0.5 * config.min_distance_px


def test_re_identification_needs_a_covariance_and_a_match_inside_the_ellipse() -> None:
    config = TrackerConfig(max_features=120, detect_every_n_frames=1)
    back = shifted(3.0, -2.0)
    source = texture(HEIGHT, WIDTH, seed=5)
    # no covariance: LK guesses only, and dropped tracks stay dropped
    tracker, first, truth = _away_and_back(config, back)
    plain = tracker.track(warped(source, back), Predictions(first.ids, truth))
    assert plain.counts.revived == 0 and not set(first.ids.tolist()) & set(plain.ids.tolist())
    # predicted 30 px off with a 3 px sigma: the point is outside the ellipse
    tracker, first, truth = _away_and_back(config, back)
    covariance = np.broadcast_to(9.0 * np.eye(2), (len(first.ids), 2, 2))
    wrong = tracker.track(warped(source, back), Predictions(first.ids, truth + 30.0, covariance))
    assert wrong.counts.searched >= 0.9 * len(first.ids)
    assert wrong.counts.revived <= 0.02 * len(first.ids)
    # too uncertain to search: a 40 px sigma (120 px half-axis, above 80)
    tracker, first, truth = _away_and_back(config, back)
    wide = np.broadcast_to(1600.0 * np.eye(2), (len(first.ids), 2, 2))
    vague = tracker.track(warped(source, back), Predictions(first.ids, truth, wide))
    assert vague.counts.revived == 0 and vague.counts.unsearched >= 0.9 * len(first.ids)


def test_a_revived_track_displaces_a_younger_one_on_the_same_corner() -> None:
    """Back at view A without predictions, new tracks start on A's corners; when the
    predictions come a frame later, the old ids return and the younger duplicates go
    (crowded), so the map point keeps its id."""
    config = TrackerConfig(max_features=120, detect_every_n_frames=1)
    back = shifted(3.0, -2.0)
    source = texture(HEIGHT, WIDTH, seed=5)
    tracker, first, _ = _away_and_back(config, back)
    unaided = tracker.track(warped(source, back))
    assert unaided.counts.new >= 50 and not set(first.ids.tolist()) & set(unaided.ids.tolist())
    again = shifted(1.0, 0.5, back)
    covariance = np.broadcast_to(16.0 * np.eye(2), (len(first.ids), 2, 2))
    result = tracker.track(
        warped(source, again), Predictions(first.ids, moved(again, first.pixels), covariance)
    )
    check_output(result, config)
    assert result.counts.revived >= 0.5 * len(first.ids)
    assert result.counts.crowded >= 0.8 * result.counts.revived
    pixels = result.pixels
    gaps = np.linalg.norm(pixels[:, None] - pixels[None], axis=2) + 1e9 * np.eye(len(pixels))
    assert np.min(gaps) >= 0.5 * config.min_distance_px


def _similarity(scale: float, degrees: float) -> np.ndarray:
    """A zoom by ``scale`` and a roll by ``degrees`` about the image centre."""
    angle = np.radians(degrees)
    linear = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    centre = np.array([(WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0])
    out = np.eye(3)
    out[:2, :2], out[:2, 2] = linear, centre - linear @ centre
    return out


def test_a_warped_template_finds_a_track_seen_larger_and_rolled() -> None:
    """Back at view A closer and rolled (x1.4, 45 deg): the template as captured no longer
    correlates, and the affine alignment of a search's peaks does not bridge so large a
    turn, so without a warp few tracks return; with the prediction's warp (the view
    change's linear part, as SLAM sends it) most return, within a pixel, and each revived
    template is captured anew (the next image tracks them on)."""
    config = TrackerConfig(max_features=120)
    back = _similarity(1.4, 45.0)
    source = texture(HEIGHT, WIDTH, seed=5)
    results = {}
    for label, warp in (('plain', None), ('warped', back[:2, :2])):
        tracker, first, truth = _away_and_back(config, back)
        inside = np.all((truth > 15.0) & (truth < [WIDTH - 15.0, HEIGHT - 15.0]), axis=1)
        ids, truth = first.ids[inside], truth[inside]
        covariance = np.broadcast_to(16.0 * np.eye(2), (len(ids), 2, 2))
        warps = None if warp is None else np.broadcast_to(warp, (len(ids), 2, 2))
        result = tracker.track(warped(source, back), Predictions(ids, truth, covariance, warps))
        check_output(result, config)
        found = by_id(result)
        errors = [np.linalg.norm(found[i] - t) for i, t in zip(ids.tolist(), truth, strict=True)
                  if i in found]  # fmt: skip
        results[label] = (len(errors), len(ids), errors)
        if warp is not None:
            after = tracker.track(warped(source, shifted(1.0, 1.0, back)))
            assert len(set(found) & set(after.ids.tolist())) >= 0.9 * len(found)
    plain, total, _ = results['plain']
    revived, total, errors = results['warped']
    assert plain <= 0.2 * total
    assert revived >= 0.8 * total and max(errors) < 1.0


def test_a_template_warped_past_recognition_is_not_searched() -> None:
    """A warp that shrinks the template below MIN_CORE_PX (seen from four times farther)
    or mirrors it: not searched, counted as unsearched, nothing revived."""
    config = TrackerConfig(max_features=120, detect_every_n_frames=1)
    back = shifted(3.0, -2.0)
    source = texture(HEIGHT, WIDTH, seed=5)
    for warp in (0.25 * np.eye(2), np.diag([1.0, -1.0])):
        tracker, first, truth = _away_and_back(config, back)
        covariance = np.broadcast_to(16.0 * np.eye(2), (len(first.ids), 2, 2))
        warps = np.broadcast_to(warp, (len(first.ids), 2, 2))
        result = tracker.track(
            warped(source, back), Predictions(first.ids, truth, covariance, warps)
        )
        assert result.counts.revived == 0
        assert result.counts.unsearched >= 0.9 * len(first.ids)
