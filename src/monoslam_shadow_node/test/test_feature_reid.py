"""Re-identification's pieces (``feature_reid``): where a template may match, and which
tracks make room for revived ones."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from monoslam_shadow_node.feature_tracker.core.feature_reid import (
    TEMPLATE_MARGIN_PX,
    Peak,
    find_peaks,
    make_room,
    refine_match,
    resolve_by_shift,
    search_core,
    search_predicted,
    search_region,
)
from monoslam_shadow_node.feature_tracker.core.feature_tracker import TrackerConfig

WIDTH, HEIGHT = 640, 480


def texture(height: int, width: int, seed: int) -> np.ndarray:
    """A smooth random grey texture (uint8)."""
    noise = np.random.default_rng(seed).uniform(0.0, 255.0, (height, width)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), 2.0)
    return np.clip((smooth - smooth.mean()) / smooth.std() * 45.0 + 128.0, 0, 255).astype(np.uint8)


def test_at_max_features_revived_map_features_displace_young_unmapped_tracks() -> None:
    """``make_room``: the youngest held tracks that no filter mapped leave first (a mapped
    one, even young, stays); only when they do not suffice do the revived with the lowest
    correlation go back to sleep."""
    ids = np.array([1, 2, 3, 4, 5, 6], np.int64)
    ages = np.array([50, 3, 1, 2, 40, 60], np.int64)
    revived = np.array([False, False, False, False, True, True])
    mapped = np.array([3, 5, 6], np.int64)  # 3 is young but a map feature
    scores = np.array([0.0, 0.0, 0.0, 0.0, 0.95, 0.85])
    out, pushed = make_room(ids, ages, revived, mapped, scores, 2)
    assert out.tolist() == [False, True, False, True, False, False] and pushed == 2
    out, pushed = make_room(ids, ages, revived, mapped, scores, 4)
    assert out.tolist() == [True, True, False, True, False, True] and pushed == 3


def test_a_look_alike_in_the_ellipse_or_a_peak_on_its_rim_is_not_a_match() -> None:
    """``find_peaks``: the template's patch alone in the ellipse is found where it is, once;
    copied a second time inside the ellipse, it is found at two places (ambiguous: no match
    unless the shared shift decides); and a patch whose best place is on the border of the
    search or the rim of the ellipse is not found there (the true peak may lie beyond)."""
    config = TrackerConfig()
    source = texture(HEIGHT, WIDTH, seed=7)
    side = config.lk_window_px + 2 * TEMPLATE_MARGIN_PX
    centre = np.array([320.0, 240.0])
    template = cv2.getRectSubPix(source, (side, side), (float(centre[0]), float(centre[1])))
    core = search_core(template, config.lk_window_px, None)
    covariance = 100.0 * np.eye(2)  # a 10 px sigma: the ellipse reaches 30 px
    region = search_region(config, source.shape, centre, covariance)
    assert isinstance(region, tuple)
    found = find_peaks(config, source, core, centre, covariance, region)
    assert len(found) == 1 and np.hypot(found[0].u - 320.0, found[0].v - 240.0) < 0.1
    twice = source.copy()
    half = side // 2
    patch = source[240 - half : 240 + half + 1, 320 - half : 320 + half + 1]
    twice[240 - half : 240 + half + 1, 345 - half : 345 + half + 1] = patch  # 25 px away
    assert len(find_peaks(config, twice, core, centre, covariance, region)) == 2
    # predicted 29.5 px to the side: the point is on the border of the searched box; 21 px
    # diagonally (2.97 sigma): inside the box, on the ellipse's rim (its neighbour is out)
    for offset in ([29.5, 0.0], [21.0, 21.0]):
        off = centre + offset
        rim = search_region(config, source.shape, off, covariance)
        assert isinstance(rim, tuple)
        peaks = find_peaks(config, source, core, off, covariance, rim)
        assert not any(np.hypot(p.u - 320.0, p.v - 240.0) < 1.0 for p in peaks)


def _template_at(source: np.ndarray, u: float, v: float) -> np.ndarray:
    side = TrackerConfig().lk_window_px + 2 * TEMPLATE_MARGIN_PX
    return np.asarray(cv2.getRectSubPix(source, (side, side), (u, v)), np.uint8)


def test_a_foreshortened_patch_is_found_once_aligned() -> None:
    """A surface slanted away from the view the template was captured in (foreshortened to
    0.67 across): the template correlates poorly where the point is (below reid_min_ncc
    without the alignment), ``refine_match`` aligns it to near 1 and finds the point within
    0.2 px, and the search reports that one place."""
    config = TrackerConfig()
    source = texture(HEIGHT, WIDTH, seed=11)
    point = np.array([300.0, 220.0])
    squeeze = np.diag([0.67, 1.0])
    affine = np.column_stack([squeeze, point - squeeze @ point])
    image = cv2.warpAffine(source, affine, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR)
    core = search_core(_template_at(source, *point), config.lk_window_px, None)
    window = core.shape[0]
    at_point = cv2.getRectSubPix(image, (window, window), (float(point[0]), float(point[1])))
    plain = float(cv2.matchTemplate(at_point, core, cv2.TM_CCOEFF_NORMED)[0, 0])
    assert plain < config.reid_min_ncc
    peak = refine_match(image, core, int(point[0]) + 1, int(point[1]))
    assert peak is not None and peak.ncc > 0.95
    assert np.hypot(peak.u - point[0], peak.v - point[1]) < 0.2
    covariance = 64.0 * np.eye(2)
    guess = point + np.array([4.0, -3.0])
    region = search_region(config, image.shape, guess, covariance)
    assert isinstance(region, tuple)
    peaks = find_peaks(config, image, core, guess, covariance, region)
    assert len(peaks) == 1 and np.hypot(peaks[0].u - point[0], peaks[0].v - point[1]) < 0.2


def test_look_alikes_are_decided_by_the_shift_the_held_features_share() -> None:
    """Two copies of a track's patch inside its ellipse: alone, the search cannot decide
    (nothing comes back); when three held map features show that the image sits 6 px right
    and 4 px up of the predictions, the copy at the prediction moved by that shift is the
    track (``resolved``), the other one is not; with only two held features, no
    decision."""
    config = TrackerConfig()
    source = texture(HEIGHT, WIDTH, seed=13)
    point = np.array([320.0, 240.0])
    template = _template_at(source, *point)
    image = source.copy()
    half = template.shape[0] // 2
    copy = source[240 - half : 240 + half + 1, 320 - half : 320 + half + 1]
    image[240 - half : 240 + half + 1, 355 - half : 355 + half + 1] = copy  # 35 px right
    shift = np.array([6.0, -4.0])
    predicted = point - shift  # the prediction misses the point by the common shift
    prediction = (
        np.array([7], np.int64),
        predicted[None],
        np.array([400.0 * np.eye(2)]),  # 20 px sigma: both copies inside
        np.zeros((1, 2, 2)),
    )
    anchors = np.array([[100.0, 100.0], [500.0, 120.0], [200.0, 400.0]])
    found, search = search_predicted(config, image, {7: template}, prediction,
                                     (np.zeros((0, 2)), np.zeros((0, 2))))  # fmt: skip
    assert found == [] and search.searched == 1
    noise = np.array([[0.3, -0.2], [-0.4, 0.1], [0.2, 0.4]])
    held = (anchors, anchors + shift + noise)
    found, search = search_predicted(config, image, {7: template}, prediction, held)
    assert len(found) == 1 and search.resolved == 1
    assert found[0][0] == 7 and np.hypot(found[0][1] - 320.0, found[0][2] - 240.0) < 0.3
    two = (anchors[:2], anchors[:2] + shift + noise[:2])
    assert search_predicted(config, image, {7: template}, prediction, two)[0] == []


def test_the_shift_decides_only_where_one_place_lies_within_its_spread() -> None:
    """``resolve_by_shift``: the radius is 3 sigma of the matches' spread about their median
    shift (at least the 1 px tracking sigma); a pending search with both places inside it,
    or none, stays undecided."""
    predicted = np.array([[100.0, 100.0], [300.0, 100.0], [200.0, 300.0], [400.0, 400.0]])
    matched = predicted + np.array([10.0, 0.0])
    matched[3, 0] += 40.0  # one wrong match: the median ignores it
    near, far = Peak(210.5, 200.0, 0.95), Peak(240.0, 200.0, 0.97)
    close = Peak(208.0, 201.0, 0.93)
    decided = resolve_by_shift(
        predicted, matched, [((200.0, 200.0), [far, near]), ((200.0, 200.0), [near, close]),
                             ((200.0, 200.0), [far])]
    )  # fmt: skip
    assert decided == [near, None, None]
    assert resolve_by_shift(predicted[:2], matched[:2], [((200.0, 200.0), [near])]) == [None]


def test_a_low_texture_patch_that_matches_as_it_is_is_not_lost_to_the_alignment() -> None:
    """A returning feature on a rendered loop (seed 0, a corner of a plain grey rectangle,
    stored in data/reid_low_texture.npz: the template's warped core and the image around
    its true point, at the centre): it correlates 0.96 as it is, but the affine alignment
    from there slides to a fit shrunk to a fifth (correlation 0.996 on a flat patch), which
    ``refine_match`` refuses; the search takes the match as it is, within 0.2 px."""
    config = TrackerConfig()
    data = np.load(Path(__file__).parent / 'data' / 'reid_low_texture.npz')
    image, core = data['image'], data['core']
    centre = np.array([40.0, 40.0])
    assert refine_match(image, core, 40, 40) is None
    covariance = 100.0 * np.eye(2)
    region = search_region(config, image.shape, centre, covariance)
    assert isinstance(region, tuple)
    peaks = find_peaks(config, image, core, centre, covariance, region)
    assert len(peaks) == 1 and peaks[0].ncc > 0.95
    assert np.hypot(peaks[0].u - 40.0, peaks[0].v - 40.0) < 0.2
