"""Re-identification's pieces (``feature_reid``): where a template may match, and which
tracks make room for revived ones."""

from __future__ import annotations

import cv2
import numpy as np

from monoslam_shadow_node.core.feature_reid import (
    TEMPLATE_MARGIN_PX,
    make_room,
    match_template,
    search_core,
    search_region,
)
from monoslam_shadow_node.core.feature_tracker import TrackerConfig

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
    """``match_template``: the template's patch alone in the ellipse is found where it is;
    copied a second time inside the ellipse, the match is ambiguous (None); and a patch whose
    best place is on the border of the search or the rim of the ellipse is refused (the true
    peak may lie beyond)."""
    config = TrackerConfig()
    source = texture(HEIGHT, WIDTH, seed=7)
    side = config.lk_window_px + 2 * TEMPLATE_MARGIN_PX
    centre = np.array([320.0, 240.0])
    template = cv2.getRectSubPix(source, (side, side), (float(centre[0]), float(centre[1])))
    core = search_core(template, config.lk_window_px, None)
    covariance = 100.0 * np.eye(2)  # a 10 px sigma: the ellipse reaches 30 px
    region = search_region(config, source.shape, centre, covariance)
    assert isinstance(region, tuple)
    found = match_template(config, source, core, centre, covariance, region)
    assert found is not None and np.hypot(found[0] - 320.0, found[1] - 240.0) < 0.1
    twice = source.copy()
    half = side // 2
    patch = source[240 - half : 240 + half + 1, 320 - half : 320 + half + 1]
    twice[240 - half : 240 + half + 1, 345 - half : 345 + half + 1] = patch  # 25 px away
    assert match_template(config, twice, core, centre, covariance, region) is None
    # predicted 29.5 px to the side: the point is on the border of the searched box; 21 px
    # diagonally (2.97 sigma): inside the box, on the ellipse's rim (its neighbour is out)
    for offset in ([29.5, 0.0], [21.0, 21.0]):
        off = centre + offset
        rim = search_region(config, source.shape, off, covariance)
        assert isinstance(rim, tuple)
        assert match_template(config, source, core, off, covariance, rim) is None
