"""A static fit implausibly near a camera waits (``near_static``): the rays of a point moving
against a camera that moves straight meet in front of it, near the lens."""

from __future__ import annotations

import numpy as np

from monoslam_shadow_node.common.core.feature_status import PENDING, STATIC
from monoslam_shadow_node.shadow_filter.core.near_static import implausibly_near
from monoslam_shadow_node.shadow_filter.core.rays import View
from monoslam_shadow_node.shadow_filter.core.shadow_classifier import ClassifierConfig
from monoslam_shadow_node.shadow_filter.core.shadow_decision import classify
from monoslam_shadow_node.shadow_filter.core.shadow_track import Track

PRIOR = (0.25, 0.25)
"""The Shadow filter's default inverse-depth prior (EkfConfig), per m."""


def _view(k: int, centre: np.ndarray, point: np.ndarray) -> View:
    direction = (point - centre) / np.linalg.norm(point - centre)
    covariance = (0.2e-2) ** 2 * (np.eye(3) - np.outer(direction, direction))
    return View(k, 1 + k * 33_333_333, centre, direction, covariance)


def test_the_distance_along_the_ray_is_judged_by_the_prior() -> None:
    views = [_view(0, np.zeros(3), np.array([0.0, 0.0, 4.0]))]
    alpha = 0.05 / 12
    assert implausibly_near(np.array([0.0, 0.0, 4.0]), views, PRIOR, alpha) is None
    assert implausibly_near(np.array([0.3, 0.0, 1.5]), views, PRIOR, alpha) is None
    near = implausibly_near(np.array([0.0, 0.0, 0.13]), views, PRIOR, alpha)
    assert near is not None and abs(near - 0.13) < 1e-9
    behind = implausibly_near(np.array([0.0, 0.0, -2.0]), views, PRIOR, alpha)
    assert behind is not None and behind < 0
    assert implausibly_near(np.array([0.0, 0.0, 0.13]), [], PRIOR, alpha) is None
    # the bound follows the prior: a prior that expects near points lets it through
    assert implausibly_near(np.array([0.0, 0.0, 0.13]), views, (8.0, 2.0), alpha) is None


def _track(speed_x: float) -> Track:
    """A point 5 m ahead moving along x at ``speed_x`` m/s, seen from a camera moving along x
    at 0.3 m/s (30 Hz, 40 views)."""
    track = Track(7, PENDING, 0, 1)
    for k in range(40):
        centre = np.array([0.01 * k, 0.0, 0.0])
        view = _view(k, centre, np.array([speed_x / 30.0 * k, 0.0, 5.0]))
        information = np.linalg.pinv(view.direction_covariance, hermitian=True)
        track.add_view(view, np.asarray(information, dtype=np.float64))
    return track


def _first_decision(
    track: Track, position: np.ndarray, prior: tuple[float, float] | None
) -> tuple[int, list[str]]:
    settings = ClassifierConfig(min_detectable_speed_m_s=0.0)  # every test decides
    warnings: list[str] = []
    for frame in range(40, 80):
        decision = classify(track, position, 0.0, frame, settings, warnings, depth_prior=prior)
        if decision is not None:
            return decision.status, warnings
    return track.status, warnings


def test_a_mover_against_a_straight_camera_path_is_not_handed_over() -> None:
    # moving at 2.7 m/s against the camera, its rays meet 0.5 m ahead: a static fit that
    # passes both tests (the motion is along the unchecked direction)
    where = np.array([0.05, 0.0, 0.5])
    status, _ = _first_decision(_track(-2.7), where, None)
    assert status == STATIC
    status, warnings = _first_decision(_track(-2.7), where, PRIOR)
    assert status == PENDING
    assert any('nearer than the depth prior allows' in w for w in warnings)
    # a static point 5 m ahead, seen the same way, is handed over with the prior as without
    status, _ = _first_decision(_track(0.0), np.array([0.0, 0.0, 5.0]), PRIOR)
    assert status == STATIC
