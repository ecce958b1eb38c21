"""The Shadow filter's EKF (eq. 1-5) and its feature lifecycle."""

from __future__ import annotations

import numpy as np
import pytest

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING, STATIC
from monoslam_shadow_node.shadow_filter.core import shadow_filter as shadow_filter_module
from monoslam_shadow_node.shadow_filter.core.rays import View
from monoslam_shadow_node.shadow_filter.core.shadow_classifier import ClassifierConfig, due_test
from monoslam_shadow_node.shadow_filter.core.shadow_decision import UNFIT_TESTS, classify, decide
from monoslam_shadow_node.shadow_filter.core.shadow_ekf import (
    EkfConfig,
    initial_states,
    predict,
    renormalize,
    static_hypothesis,
    update,
    world_estimates,
)
from monoslam_shadow_node.shadow_filter.core.shadow_filter import (
    FrameInput,
    InputError,
    ShadowConfig,
    ShadowFilter,
)
from monoslam_shadow_node.shadow_filter.core.shadow_track import Track
from monoslam_shadow_node.shadow_filter.core.static_fit import motion_score_test
from slam_core.camera import CameraModel
from slam_core.geometry.so3 import rotation_from_vector
from slam_core.testing.jacobians import assert_jacobian_close

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320], [0, 300, 240], [0, 0, 1]]), np.array([-0.05, 0, 0, 0, 0])
)


def _states(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    directions = rng.normal(0, 0.2, (count, 3)) + np.array([0.0, 0.0, 1.0])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    states, covariances = initial_states(
        directions, np.tile(1e-6 * np.eye(3), (count, 1, 1)), EkfConfig()
    )
    states[:, 3] = rng.uniform(0.1, 0.5, count)
    states[:, 4:] = states[:, 3:4] * rng.normal(0, 0.5, (count, 3))  # u = w v
    return states, covariances


def test_predict_moves_a_point_like_the_camera_motion_says() -> None:
    rotation, translation = (
        rotation_from_vector(np.array([0.01, -0.02, 0.03])),
        np.array([0.05, 0, -0.1]),
    )
    point, velocity, dt = np.array([0.4, -0.2, 4.0]), np.array([0.3, 0.1, -0.2]), 0.1
    w = 1 / np.linalg.norm(point)
    state = np.concatenate([point * w, [w], w * velocity])  # u = w v
    moved, _ = predict(state[None], np.eye(7)[None] * 1e-4, rotation, translation, dt, EkfConfig())
    expected = rotation @ (point + velocity * dt) + translation
    np.testing.assert_allclose(moved[0, :3] / moved[0, 3], expected, rtol=1e-12)
    np.testing.assert_allclose(moved[0, 4:] / moved[0, 3], rotation @ velocity, rtol=1e-12)
    assert np.linalg.norm(moved[0, :3]) == pytest.approx(1.0)


def test_predict_covariance_uses_the_motion_jacobian() -> None:
    """With no process noise the predicted covariance is J P J' through the normalization:
    checked against finite differences of the whole (motion + renormalization) map."""
    rng = np.random.default_rng(3)
    states, _ = _states(rng, 1)
    rotation, translation = (
        rotation_from_vector(np.array([0.02, 0.01, -0.01])),
        np.array([0.1, 0.0, 0.05]),
    )
    config = EkfConfig(acceleration_psd_m2_s3=0.0)

    def motion(x: np.ndarray) -> np.ndarray:
        moved, _ = predict(x[None], np.zeros((1, 7, 7)), rotation, translation, 0.05, config)
        return moved[0]

    covariance = np.diag(rng.uniform(1e-4, 1e-2, 7))
    _, predicted = predict(states, covariance[None], rotation, translation, 0.05, config)
    jacobian = np.zeros((7, 7))
    eps = 1e-6
    for c in range(7):
        step = np.zeros(7)
        step[c] = eps
        jacobian[:, c] = (motion(states[0] + step) - motion(states[0] - step)) / (2 * eps)
    np.testing.assert_allclose(predicted[0], jacobian @ covariance @ jacobian.T, atol=1e-9)


def test_renormalize_jacobian_and_static_hypothesis() -> None:
    rng = np.random.default_rng(5)
    states, covariances = _states(rng, 3)
    scaled = states * 2.0  # the whole homogeneous state (X0, w, u) scales together
    unit, _ = renormalize(scaled, covariances)
    np.testing.assert_allclose(unit, states, atol=1e-12)
    assert_jacobian_close(
        _renormalize_jacobian(scaled[0]),
        lambda x: renormalize(x[None], np.zeros((1, 7, 7)))[0][0],
        scaled[0],
        atol=1e-8,
    )
    covariance = np.eye(7) * 1e-2
    covariance[3, 4] = covariance[4, 3] = 5e-3  # depth correlated with velocity
    conditioned, reduced = static_hypothesis(states[:1], covariance[None])
    assert np.all(conditioned[0, 4:] == 0) and np.all(reduced[0, 4:, 4:] == 0)
    assert reduced[0, 3, 3] == pytest.approx(1e-2 - 5e-3**2 / 1e-2)


def _renormalize_jacobian(state: np.ndarray) -> np.ndarray:
    """d(renormalized)/d(state) by the formula in shadow_ekf.renormalize's docstring."""
    norm = np.linalg.norm(state[:3])
    unit = np.concatenate([state[:3] / norm, np.zeros(4)])
    return (np.eye(7) - np.outer(state / norm, unit)) / norm


def test_world_estimates_propagate_position_and_velocity_by_their_jacobians() -> None:
    rng = np.random.default_rng(8)
    states, _ = _states(rng, 1)
    rotation, centre = rotation_from_vector(np.array([0.1, -0.3, 0.2])), np.array([1.0, 2.0, 0.5])
    covariance = np.diag(rng.uniform(1e-6, 1e-4, 7))

    def world(x: np.ndarray) -> np.ndarray:
        estimate = world_estimates(x[None], covariance[None], rotation, centre)
        return np.concatenate([estimate.position[0], estimate.velocity[0]])

    estimate = world_estimates(states, covariance[None], rotation, centre)
    point = rotation @ (states[0, :3] / states[0, 3]) + centre
    np.testing.assert_allclose(estimate.position[0], point, rtol=1e-12)
    np.testing.assert_allclose(estimate.velocity[0], rotation @ states[0, 4:] / states[0, 3])
    jacobian = np.zeros((6, 7))
    for c in range(7):
        step = np.zeros(7)
        step[c] = 1e-7
        jacobian[:, c] = (world(states[0] + step) - world(states[0] - step)) / 2e-7
    expected = jacobian @ covariance @ jacobian.T
    np.testing.assert_allclose(estimate.position_covariance[0], expected[:3, :3], atol=1e-10)
    np.testing.assert_allclose(estimate.velocity_covariance[0], expected[3:, 3:], atol=1e-10)


def test_tracker_only_mode_keeps_every_feature_pending() -> None:
    shadow = ShadowFilter(CAMERA, ShadowConfig(classify=False))
    rng = np.random.default_rng(4)
    points = np.column_stack(
        [rng.uniform(3, 7, 60), rng.uniform(-1, 1.5, 60), rng.uniform(0.5, 2.5, 60)]
    )
    velocities = np.zeros((60, 3))
    velocities[40:] = rng.normal(0, 0.5, (20, 3))
    for frame in _scene_frames(velocities, points, rng):
        result = shadow.process(frame)
        assert not result.decisions and not result.handovers
    assert len(result.tracks) > 40 and {track.status for track in result.tracks} == {PENDING}
    with pytest.raises(ValueError, match='classify'):
        ShadowConfig(classify=1)  # type: ignore[arg-type]


def test_update_pulls_the_estimate_to_the_measurement_and_gates_outliers() -> None:
    rng = np.random.default_rng(1)
    states, covariances = _states(rng, 2)
    covariances[:, :3, :3] = 1e-4 * np.eye(3)
    predicted = CAMERA.project(states[:, :3])
    measured = predicted + np.array([[2.0, -1.0], [400.0, 0.0]])  # the second: a gross outlier
    result = update(states, covariances, measured, CAMERA, EkfConfig())
    assert result.used.tolist() == [True, False]
    after = CAMERA.project(result.states[:1, :3])
    assert np.linalg.norm(after - measured[:1]) < np.linalg.norm(predicted[:1] - measured[:1])
    assert np.trace(result.covariances[0]) < np.trace(covariances[0])
    assert np.all(np.linalg.eigvalsh(result.covariances[0]) > -1e-12)


def _scene_frames(
    velocities: np.ndarray, points: np.ndarray, rng: np.random.Generator, frames: int = 150
) -> list[FrameInput]:
    out = []
    for k in range(frames):
        t = k / 30.0
        centre = np.array([0.3 * np.sin(0.8 * t), 0.6 * t, 1.5 + 0.2 * np.sin(1.3 * t)])
        forward = np.array([1.0, 0.05 * np.sin(t), -0.05])
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        rotation = np.column_stack([right, np.cross(forward, right), forward])
        camera_points = (points + velocities * t - centre) @ rotation
        pixels = CAMERA.project(camera_points) + rng.normal(0, 1.0, (len(points), 2))
        out.append(
            FrameInput(k * 33_333_333 + 1, rotation, centre, np.arange(len(points)), pixels)
        )
    return out


def _run_scene(config: ShadowConfig) -> tuple[dict[int, int], dict[int, object], np.ndarray]:
    rng = np.random.default_rng(11)
    count = 60
    points = np.column_stack(
        [rng.uniform(3, 7, count), rng.uniform(-1.0, 1.5, count), rng.uniform(0.5, 2.5, count)]
    )
    velocities = np.zeros((count, 3))
    velocities[40:, 2] = rng.choice([-0.5, 0.5], 20)  # 20 points moving vertically
    shadow = ShadowFilter(CAMERA, config)
    status: dict[int, int] = {}
    handed: dict[int, object] = {}
    for frame in _scene_frames(velocities, points, rng):
        result = shadow.process(frame)
        for decision in result.decisions:
            status[decision.id] = decision.status
        for handover in result.handovers:
            handed[handover.id] = handover
        for track in result.tracks:
            assert np.all(np.isfinite(track.position)) and np.all(np.isfinite(track.velocity))
            assert np.all(np.isfinite(track.position_covariance))
    assert set(handed) <= shadow.released_ids
    return status, handed, points


def test_lifecycle_static_points_are_handed_over_and_moving_ones_tracked() -> None:
    """Without the motion-visibility rule (min_detectable_speed_m_s 0) every accepted test
    decides: most static points are handed over with a consistent position, most moving
    points are called DYNAMIC."""
    config = ShadowConfig(classifier=ClassifierConfig(min_detectable_speed_m_s=0.0))
    status, handed, points = _run_scene(config)
    moving = [status.get(i, PENDING) for i in range(40, 60)]
    static = [status.get(i, PENDING) for i in range(40)]
    assert moving.count(DYNAMIC) >= 18
    assert static.count(STATIC) >= 34
    errors = []
    for track_id, handover in handed.items():
        assert status[track_id] == STATIC
        if track_id >= 40:
            continue  # a moving point handed over: its position is not a fixed one
        error = handover.position - points[track_id]  # type: ignore[attr-defined]
        covariance = handover.position_covariance  # type: ignore[attr-defined]
        errors.append(error @ np.linalg.solve(covariance, error))
    assert np.mean(errors) < 6.0  # triangulated from all views: consistent (NEES ~ 3)
    assert max(errors) < 30.0


def test_default_rule_hands_over_only_where_motion_would_have_been_visible() -> None:
    """The default rule: every moving point DYNAMIC, none handed over; the static points
    handed over were decided only once 0.3 m/s along all but the least visible direction
    would have been seen (so later than without the rule), and at most 4 of the 40 are false
    alarms. The strict rule (no direction unchecked) waits longer still."""
    status, handed, _ = _run_scene(ShadowConfig())
    assert all(status.get(i) == DYNAMIC for i in range(40, 60))
    assert not set(handed) & set(range(40, 60))
    assert len(handed) >= 30
    assert sum(status.get(i) == DYNAMIC for i in range(40)) <= 4
    quick = _run_scene(ShadowConfig(classifier=ClassifierConfig(min_detectable_speed_m_s=0.0)))
    strict = _run_scene(ShadowConfig(classifier=ClassifierConfig(unchecked_directions=0)))
    runs = {'quick': quick[1], 'default': handed, 'strict': strict[1]}
    frames = {
        name: np.median([h.frame for h in given.values()])  # type: ignore[attr-defined]
        for name, given in runs.items()
        if given
    }
    assert frames['quick'] < frames['default']
    assert 'strict' not in frames or frames['strict'] > frames['default']


def test_a_revoked_feature_comes_back_as_a_suspect_with_fresh_views(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    rng = np.random.default_rng(11)
    count = 40
    points = np.column_stack(
        [rng.uniform(3, 7, count), rng.uniform(-1.0, 1.5, count), rng.uniform(0.5, 2.5, count)]
    )
    shadow = ShadowFilter(CAMERA, ShadowConfig())
    frames = _scene_frames(np.zeros((count, 3)), points, rng, frames=150)
    handed: list[int] = []
    index = 0
    while not handed:
        handed = [h.id for h in shadow.process(frames[index]).handovers]
        index += 1
    revoked = handed[0]
    assert shadow.revoke([revoked, 10_000]) == [revoked]  # 10000 was never handed over
    assert shadow.suspect_ids == {revoked} and revoked not in shadow.released_ids
    rules: dict[bool, set[int]] = {True: set(), False: set()}

    def spy(track, position, visibility, frame, settings, noise):  # type: ignore[no-untyped-def]
        rules[track.id == revoked].add(settings.unchecked_directions)
        return due_test(track, position, visibility, frame, settings, noise)

    monkeypatch.setattr(shadow_filter_module, 'due_test', spy)
    result = shadow.process(frames[index])
    (report,) = [t for t in result.tracks if t.id == revoked]
    assert report.status == PENDING and report.first_frame == index  # fresh views only
    for frame in frames[index + 1 :]:
        shadow.process(frame)
    assert rules == {True: {0}, False: {1}}  # the suspect is judged by the strict rule


def test_the_filter_judges_static_fits_by_its_own_inverse_depth_prior(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """ShadowFilter hands its EKF's inverse-depth prior to the decision, which makes a static
    fit implausibly near a camera wait (near_static)."""
    ekf = EkfConfig(initial_inverse_depth_per_m=0.2, initial_inverse_depth_sigma_per_m=0.3)
    priors: list[object] = []

    def spy(*args, **kwargs):  # type: ignore[no-untyped-def]
        priors.append(args[6] if len(args) > 6 else kwargs.get('depth_prior'))
        return decide(*args, **kwargs)

    monkeypatch.setattr(shadow_filter_module, 'decide', spy)
    rng = np.random.default_rng(11)
    points = np.column_stack([rng.uniform(3, 7, 20), rng.uniform(-1, 1.5, 20), np.ones(20)])
    shadow = ShadowFilter(CAMERA, ShadowConfig(ekf=ekf))
    for frame in _scene_frames(np.zeros((20, 3)), points, rng, frames=90):
        shadow.process(frame)
    assert priors and all(prior == (0.2, 0.3) for prior in priors)


def test_bad_input_is_named_and_leaves_the_filter_usable() -> None:
    shadow = ShadowFilter(CAMERA)
    ids, pixels = np.array([1, 2]), np.array([[300.0, 200.0], [np.nan, 100.0]])
    first = shadow.process(FrameInput(10, np.eye(3), np.zeros(3), ids, pixels))
    assert any('non-finite pixels: ids 2' in w for w in first.warnings)
    assert [t.id for t in first.tracks] == [1] and first.tracks[0].status == PENDING
    with pytest.raises(InputError, match='not after the previous frame'):
        shadow.process(FrameInput(10, np.eye(3), np.zeros(3), ids[:1], pixels[:1]))
    with pytest.raises(InputError, match='rotation'):
        shadow.process(FrameInput(20, np.full((3, 3), np.nan), np.zeros(3), ids, pixels))
    with pytest.raises(InputError, match='repeat'):
        shadow.process(FrameInput(20, np.eye(3), np.zeros(3), np.array([1, 1]), pixels))
    # zero baseline: the camera never moves, nothing is ever decided, nothing is NaN
    for k in range(1, 40):
        result = shadow.process(FrameInput(10 + k, np.eye(3), np.zeros(3), ids[:1], pixels[:1]))
        assert not result.decisions
        assert all(np.all(np.isfinite(t.position)) for t in result.tracks)
    assert shadow.frame_count == 40


def test_invalid_classifier_settings_name_the_field() -> None:
    with pytest.raises(ValueError, match=r'alpha=1\.5'):
        ClassifierConfig(alpha=1.5)
    with pytest.raises(ValueError, match='max_tests=0'):
        ClassifierConfig(max_tests=0)
    with pytest.raises(ValueError, match='pixel_sigma_px'):
        EkfConfig(pixel_sigma_px=0.0)


def test_a_feature_that_keeps_missing_the_gate_restarts_its_filter() -> None:
    """A feature whose pixel jumps far from its prediction (it moved faster than the process
    noise allows) is gated out, and after three such frames its EKF restarts from the new
    ray and follows it again; its id stays."""
    shadow = ShadowFilter(CAMERA)
    rotation, ids = np.eye(3), np.array([7])
    warnings: list[str] = []
    for k in range(12):
        pixel = [320.0 + k, 240.0] if k < 6 else [120.0 + k, 60.0]
        centre = np.array([0.02 * k, 0.0, 0.0])
        result = shadow.process(FrameInput(1 + k * 33_000_000, rotation, centre, ids, [pixel]))
        warnings += result.warnings
        assert [t.id for t in result.tracks] == [7]
    assert sum('outside the innovation gate' in w for w in warnings) >= 3
    assert any('restarts from this ray' in w for w in warnings)
    state = shadow._states[0]  # the restarted filter predicts the new pixel again
    assert np.linalg.norm(CAMERA.project(state[None, :3]) - [131.0, 60.0]) < 5.0


def _diverging_track(speed_x: float) -> Track:
    """A track seen from cameras moving along x at 0.3 m/s (30 Hz, 40 views) of a point 5 m
    ahead moving along x at ``speed_x``: faster than the camera, the rays meet behind it."""
    track = Track(7, PENDING, 0, 1)
    for k in range(40):
        centre = np.array([0.01 * k, 0.0, 0.0])
        point = np.array([speed_x / 30.0 * k, 0.0, 5.0])
        direction = (point - centre) / np.linalg.norm(point - centre)
        covariance = (0.2e-2) ** 2 * (np.eye(3) - np.outer(direction, direction))
        view = View(k, 1 + k * 33_333_333, centre, direction, covariance)
        track.add_view(view, np.linalg.pinv(covariance, hermitian=True))
    return track


def test_views_that_keep_refusing_a_static_point_are_evidence_of_motion() -> None:
    # past the parallax milestone, the all-view fit lands behind the cameras at three tests in
    # a row (retried every other frame): DYNAMIC, without a test statistic
    track = _diverging_track(0.6)
    position = np.array([0.2, 0.0, 5.0])  # where the EKF, conditioned on v = 0, puts it
    assert motion_score_test(track.views, 0.01, position) is None
    settings = ClassifierConfig()
    decisions, warnings = [], []
    for frame in range(40, 60):
        decision = classify(track, position, 0.0, frame, settings, warnings)
        if decision is not None:
            decisions.append((frame, decision))
            break  # decided: no longer PENDING, the filter classifies it no more
    ((frame, decision),) = decisions
    assert decision.status == DYNAMIC and np.isnan(decision.statistic) and track.unfit == 3
    assert frame <= 40 + 2 * UNFIT_TESTS and len(warnings) == UNFIT_TESTS - 1
    # a static point seen the same way is tested as usual (never 'unfit')
    static = _diverging_track(0.0)
    for frame in range(40, 60):
        classify(static, np.array([0.0, 0.0, 5.0]), 0.0, frame, settings, [])
    assert static.unfit == 0 and static.tests_run >= 1


def test_score_test_declines_views_that_do_not_fix_a_point() -> None:
    """Views from one camera centre (no baseline) or along one line cannot fix a static
    point: the score test returns None instead of raising."""
    direction = np.array([0.0, 0.0, 1.0])
    covariance = 1e-5 * (np.eye(3) - np.outer(direction, direction))
    views = [View(k, 1 + k * 33_000_000, np.zeros(3), direction, covariance) for k in range(10)]
    assert motion_score_test(views, 0.01, np.array([0.0, 0.0, 5.0])) is None
    along = [
        View(k, 1 + k * 33_000_000, np.array([0.0, 0.0, 0.1 * k]), direction, covariance)
        for k in range(10)
    ]
    assert motion_score_test(along, 0.01, np.array([0.0, 0.0, 5.0])) is None


@pytest.mark.parametrize('name', ['both', 'three_ray', 'all_view'])
def test_each_static_test_behind_the_seam_decides_the_scene(name: str) -> None:
    """One parameter chooses the test (``static_test``): each alone, at alpha / max_tests,
    and both together, at half that, separate the scene's static points from the movers."""
    classifier = ClassifierConfig(static_test=name)
    assert classifier.test_alpha == pytest.approx(
        classifier.alpha / ((2 if name == 'both' else 1) * classifier.max_tests)
    )
    status, handed, _ = _run_scene(ShadowConfig(classifier=classifier))
    assert sum(status.get(i) == DYNAMIC for i in range(40, 60)) >= 18
    assert not set(handed) & set(range(40, 60))
    assert len(handed) >= 28
    assert sum(status.get(i) == DYNAMIC for i in range(40)) <= 4


def test_the_static_test_parameter_chooses_the_statistic_that_decides() -> None:
    """The decisions carry the deciding test's statistic: the three-ray T with ``three_ray``
    and ``both``, the score test's T with ``all_view``."""
    statistics = {}
    for name in ('both', 'three_ray', 'all_view'):
        rng = np.random.default_rng(11)
        points = np.column_stack(
            [rng.uniform(3, 7, 60), rng.uniform(-1.0, 1.5, 60), rng.uniform(0.5, 2.5, 60)]
        )
        velocities = np.zeros((60, 3))
        velocities[40:, 2] = rng.choice([-0.5, 0.5], 20)
        shadow = ShadowFilter(CAMERA, ShadowConfig(classifier=ClassifierConfig(static_test=name)))
        statistics[name] = {
            decision.id: decision.statistic
            for frame in _scene_frames(velocities, points, rng)
            for decision in shadow.process(frame).decisions
            if decision.status == STATIC
        }
    three_ray, all_view, both = statistics['three_ray'], statistics['all_view'], statistics['both']
    shared = set(three_ray) & set(all_view)
    assert len(shared) >= 20
    assert all(three_ray[i] != all_view[i] for i in shared)
    with_both = set(both) & set(all_view)
    assert len(with_both) >= 20 and all(both[i] != all_view[i] for i in with_both)
    # decided in the same image (its alpha is halved, so not always), both carries the three-ray T
    assert any(both[i] == three_ray[i] for i in set(both) & set(three_ray))


def test_an_unknown_static_test_is_named() -> None:
    with pytest.raises(ValueError, match="static_test='pluecker'"):
        ClassifierConfig(static_test='pluecker')
