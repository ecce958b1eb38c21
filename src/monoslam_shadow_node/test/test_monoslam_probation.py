"""MonoSLAM's probation for handed-over features (ROS-free): a feature on probation is
measured with a Schmidt ('consider') update that corrects only its own block, so a group of
them that agrees on a wrong camera cannot move the camera; the update is the Joseph form for
that gain; a handover enters on probation and leaves it when it becomes Euclidean."""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_ekf import (
    MIN_TRUSTED_POINTS,
    consider_update,
    gated_update,
    linearize_all,
    matches,
    measurement_variance,
)
from monoslam_shadow_node.monoslam.core.monoslam_model import (
    CAMERA_SIZE,
    EUCLIDEAN_SIZE,
    Q_SLICE,
    R_SLICE,
    V_SLICE,
    W_SLICE,
    project_feature,
)
from monoslam_shadow_node.monoslam.core.monoslam_ransac import ransac_update
from monoslam_shadow_node.monoslam.core.monoslam_state import FeatureBlock, FilterState
from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig
from slam_core.camera import CameraModel

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320.0], [0, 300.0, 240.0], [0, 0, 1]]), np.zeros(5)
)  # fmt: skip
CONFIG = MonoSlamConfig()
FEATURES = 20
GROUP = range(12, 20)
"""Eight features that move together (a rigid mover): on probation in the tests."""
SHIFT_PX = (2.5, -1.5)
FRAMES = 130
"""Their common image shift: inside the low-innovation band, so RANSAC counts them in."""


def _state(rng: np.random.Generator) -> FilterState:
    """The camera at the origin looking along +z (position sigma 0.05 m) and FEATURES Euclidean
    points 3-6 m ahead (sigma 0.2 m along each axis), correlated with nothing."""
    state = FilterState()
    camera = np.zeros(CAMERA_SIZE)
    camera[Q_SLICE] = [1.0, 0.0, 0.0, 0.0]
    depth = rng.uniform(3.0, 6.0, FEATURES)
    lateral = rng.uniform(-0.6, 0.6, (FEATURES, 2)) * depth[:, None]
    state.x = np.concatenate([camera, np.column_stack([lateral, depth]).reshape(-1)])
    variances = np.full(len(state.x), 0.2**2)
    variances[R_SLICE] = 0.05**2
    variances[Q_SLICE] = [1e-12, *(3 * [0.005**2])]
    variances[V_SLICE] = variances[W_SLICE] = 0.01
    state.p = np.diag(variances)
    state.features = [
        FeatureBlock(i, CAMERA_SIZE + EUCLIDEAN_SIZE * i, EUCLIDEAN_SIZE, None, 'handover', 0, 0)
        for i in range(FEATURES)
    ]
    return state


def _observed(state: FilterState, rng: np.random.Generator) -> dict[int, np.ndarray]:
    """Pixels from the estimated camera with 0.3 px noise; the group's shifted by SHIFT_PX."""
    observed = {}
    for feature in state.features:
        point = state.x[feature.start : feature.start + feature.size]
        pixel = project_feature(CAMERA, state.x[:CAMERA_SIZE], point, None)[0]
        observed[feature.id] = pixel + rng.normal(0.0, 0.3, 2)
        if feature.id in GROUP:
            observed[feature.id] += SHIFT_PX
    return observed


def _on_probation(state: FilterState) -> FilterState:
    out = copy.deepcopy(state)
    for feature in out.features:
        feature.probation = feature.id in GROUP
    return out


def test_features_on_probation_do_not_move_the_camera() -> None:
    rng = np.random.default_rng(0)
    prior = _state(rng)
    observed = _observed(prior, rng)
    without_group = {i: pixel for i, pixel in observed.items() if i not in GROUP}
    for update in ('ransac', 'gated'):
        reference = copy.deepcopy(prior)
        probation = _on_probation(prior)
        trusted = copy.deepcopy(prior)
        if update == 'ransac':
            ransac_update(reference, CAMERA, without_group, [], CONFIG, np.random.default_rng(1))
            outcome = ransac_update(
                probation, CAMERA, observed, [], CONFIG, np.random.default_rng(1)
            )
            ransac_update(trusted, CAMERA, observed, [], CONFIG, np.random.default_rng(1))
        else:
            gated_update(reference, CAMERA, without_group, [], CONFIG)
            outcome = gated_update(probation, CAMERA, observed, [], CONFIG)
            gated_update(trusted, CAMERA, observed, [], CONFIG)
        assert outcome.counts.probation == len(GROUP) and outcome.rejected == []
        camera = slice(0, CAMERA_SIZE)
        # the camera (and the other features) as if the group had not been seen at all
        others = np.r_[camera, CAMERA_SIZE : CAMERA_SIZE + EUCLIDEAN_SIZE * GROUP.start]
        np.testing.assert_allclose(probation.x[others], reference.x[others], atol=1e-12)
        np.testing.assert_allclose(
            probation.p[np.ix_(others, others)], reference.p[np.ix_(others, others)], atol=1e-15
        )
        # trusted, the same group drags the camera by a sizeable share of its sigma
        sigma = np.sqrt(np.diag(reference.p))[R_SLICE]
        dragged = np.abs(trusted.x[R_SLICE] - reference.x[R_SLICE]) / sigma
        assert np.max(dragged) > 0.1
        # each group member moved itself towards its shifted pixel
        for feature in probation.features[GROUP.start :]:
            block = slice(feature.start, feature.start + feature.size)
            pixel = project_feature(CAMERA, probation.x[:CAMERA_SIZE], probation.x[block], None)[0]
            before = project_feature(CAMERA, prior.x[:CAMERA_SIZE], prior.x[block], None)[0]
            assert np.linalg.norm(observed[feature.id] - pixel) < np.linalg.norm(
                observed[feature.id] - before
            )
        assert np.min(np.linalg.eigvalsh(probation.p)) > -1e-12  # PSD (q's norm: 0)
        np.testing.assert_array_equal(probation.p, probation.p.T)


def test_the_consider_update_is_the_joseph_form_of_the_schmidt_gain() -> None:
    rng = np.random.default_rng(2)
    state = _state(rng)
    n = len(state.x)
    mixing = np.eye(n) + 0.05 * rng.normal(size=(n, n))  # correlate everything
    state.p = mixing @ state.p @ mixing.T
    feature = state.features[4]
    observed = {feature.id: _observed(state, rng)[feature.id] + 2.0}
    match = matches(state, observed, [])[0]
    linearized = linearize_all(state, CAMERA, [match])[0]
    assert linearized is not None and linearized.block is not None
    sigma2 = measurement_variance(match, CONFIG)
    h = linearized.row(n)
    s = h @ state.p @ h.T + sigma2 * np.eye(2)
    gain = np.zeros((n, 2))
    gain[linearized.block] = (state.p @ h.T)[linearized.block] @ np.linalg.inv(s)
    factor = np.eye(n) - gain @ h
    expected_p = factor @ state.p @ factor.T + sigma2 * gain @ gain.T
    expected_x = state.x + gain @ (match.pixel - linearized.predicted)
    consider_update(state, match, linearized, sigma2)
    np.testing.assert_allclose(state.x, expected_x, atol=1e-12)
    np.testing.assert_allclose(state.p, expected_p, atol=1e-12)
    untouched = np.ones(n, dtype=bool)
    untouched[linearized.block] = False
    assert np.all(gain[untouched] == 0.0)


# a target's four corners: known points, certain, that fix the camera on their own (a feature
# stays on probation although fewer than MIN_TRUSTED_POINTS are trusted)
CORNERS = np.array([[-0.3, -0.3, 4.0], [0.3, -0.3, 4.0], [0.3, 0.3, 4.0], [-0.3, 0.3, 4.0]])
POINT = np.array([0.8, 0.2, 2.5])


def _walk(config: MonoSlamConfig, handover: bool) -> list[tuple[int, bool] | None]:
    """Run MonoSLAM with CORNERS known while the camera walks sideways at 0.6 m/s (POINT's
    parallax grows), POINT tracked as feature 7 from frame 2 (handed over at frame 1 when
    ``handover``); return per frame (size, probation) of the first feature in the state."""
    from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
    from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamFrame

    known = {k: tuple(point) for k, point in enumerate(CORNERS)}
    slam = MonoSlam(CAMERA, dataclasses.replace(config, known_points=known))
    camera_x = np.zeros(CAMERA_SIZE)
    camera_x[Q_SLICE] = [1.0, 0.0, 0.0, 0.0]
    states: list[tuple[int, bool] | None] = []
    for frame in range(FRAMES):
        camera_x[R_SLICE] = [0.02 * frame, 0.0, 0.0]
        pixels = np.array([project_feature(CAMERA, camera_x, c, None)[0] for c in CORNERS])
        feature_pixel = project_feature(CAMERA, camera_x, POINT, None)[0]
        ids = np.array([7] if frame >= 2 else [], dtype=np.int64)
        result = slam.process(
            MonoSlamFrame(
                int(frame * 1e9 / 30), ids, feature_pixel.reshape(-1, 2)[: len(ids)],
                np.arange(len(CORNERS), dtype=np.int64), pixels,
            )
        )  # fmt: skip
        if frame == 1 and handover:
            assert slam.add_handover(7, POINT, 0.04 * np.eye(3)) is None
        features = slam._state.features
        states.append((features[0].size, features[0].probation) if features else None)
        assert result.status == 'tracking'
        assert not math.isnan(float(slam._state.x[R_SLICE][0]))
    return states


def _waits_until_euclidean(
    states: list[tuple[int, bool] | None], first: int, probation: bool = True
) -> None:
    """The feature entered at ``first`` as inverse depth (on ``probation``) and was off
    probation once it became Euclidean."""
    euclidean = [k for k, s in enumerate(states) if s is not None and s[0] == EUCLIDEAN_SIZE]
    assert euclidean, 'the feature never became Euclidean'
    assert all(states[k] == (EUCLIDEAN_SIZE, False) for k in euclidean)
    assert all(s == (6, probation) for s in states[first : euclidean[0]])


def test_a_handover_enters_on_probation_and_leaves_it_when_euclidean() -> None:
    for probation in (True, False):
        config = MonoSlamConfig(initialize='handover', handover_probation=probation)
        states = _walk(config, handover=True)
        assert states[2] == (6, probation)  # entered as inverse depth, on probation if set
        _waits_until_euclidean(states, 2, probation)


def test_probation_ends_when_too_few_others_to_find_a_wrong_one_are_measured() -> None:
    """With fewer trusted measurements than it takes to find a wrong one among them
    (monoslam_ekf.MIN_TRUSTED_POINTS), the cleared features on probation leave it and update
    the camera (monoslam_ekf's docstring)."""
    rng = np.random.default_rng(3)
    prior = _state(rng)
    observed = _observed(prior, rng)
    trusted_seen = {i: p for i, p in observed.items() if i in GROUP or i < MIN_TRUSTED_POINTS - 1}
    for update in ('ransac', 'gated'):
        state = _on_probation(prior)
        if update == 'ransac':
            outcome = ransac_update(
                state, CAMERA, trusted_seen, [], CONFIG, np.random.default_rng(1)
            )
        else:
            outcome = gated_update(state, CAMERA, trusted_seen, [], CONFIG)
        assert outcome.counts.probation == 0
        assert not any(feature.probation for feature in state.features if feature.id in GROUP)
        moved = np.abs(state.x[R_SLICE] - prior.x[R_SLICE]) / np.sqrt(np.diag(prior.p)[R_SLICE])
        assert np.max(moved) > 0.05  # the shifted group now moves the camera
        # with that many trusted features seen, the group stays on probation
        state = _on_probation(prior)
        enough = {i: p for i, p in observed.items() if i in GROUP or i < MIN_TRUSTED_POINTS}
        gated_update(state, CAMERA, enough, [], CONFIG)
        assert all(feature.probation for feature in state.features if feature.id in GROUP)


def test_four_trusted_measurements_do_not_keep_the_cleared_features_on_probation() -> None:
    """Four trusted measurements fix a pose with one to spare, which shows that one is wrong
    but not which: the cleared features on probation in view join the update (on Bonn crowd
    the camera left the truth while four to seven trusted features fixed it, one of them
    wrong; docs/design/monoslam.md, "Too few trusted measurements")."""
    rng = np.random.default_rng(3)
    prior = _state(rng)
    observed = _observed(prior, rng)
    four = {i: p for i, p in observed.items() if i in GROUP or i < 4}
    state = _on_probation(prior)
    outcome = ransac_update(state, CAMERA, four, [], CONFIG, np.random.default_rng(1))
    assert outcome.counts.probation == 0
    assert not any(feature.probation for feature in state.features if feature.id in GROUP)


def test_a_new_feature_waits_on_probation_with_new_probation() -> None:
    """initialize='all' with new_probation: a new feature enters on probation (it corrects
    only itself) and leaves it when Euclidean, as a handover does; without it, classic
    MonoSLAM, it moves the camera from its first measurement."""
    for probation in (True, False):
        states = _walk(MonoSlamConfig(initialize='all', new_probation=probation), handover=False)
        first = next(k for k, s in enumerate(states) if s is not None)
        assert states[first] == (6, probation)
        if probation:
            _waits_until_euclidean(states, first)
        else:
            assert not any(s[1] for s in states[first:] if s is not None)
