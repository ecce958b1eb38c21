"""MonoSLAM's 1-point RANSAC update on a small synthetic state (ROS-free): it rejects wrong
matches the gate lets through, rescues consistent high-innovation ones, is reproducible for a
seed, and ``update='gated'`` keeps the plain gated update."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from monoslam_shadow_node.monoslam.core.monoslam_ekf import (
    apply_update,
    gate_all,
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
from monoslam_shadow_node.monoslam.core.monoslam_ransac import (
    hypotheses_needed,
    previewed,
    ransac_update,
)
from monoslam_shadow_node.monoslam.core.monoslam_state import FeatureBlock, FilterState
from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig
from slam_core.camera import CameraModel

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320.0], [0, 300.0, 240.0], [0, 0, 1]]), np.zeros(5)
)  # fmt: skip
CONFIG = MonoSlamConfig()
POSITION_SIGMA_M = 0.02
ANGLE_SIGMA_RAD = 0.005
POINT_SIGMA_M = 0.01
FEATURES = 20


def _state(rng: np.random.Generator, uncertain: int | None = None) -> FilterState:
    """The camera at the origin looking along +z and FEATURES Euclidean points 3-6 m ahead
    (feature ids 0..FEATURES-1); ``uncertain``: that feature's position sigma is 0.1 m."""
    state = FilterState()
    camera = np.zeros(CAMERA_SIZE)
    camera[Q_SLICE] = [1.0, 0.0, 0.0, 0.0]
    depth = rng.uniform(3.0, 6.0, FEATURES)
    lateral = rng.uniform(-0.6, 0.6, (FEATURES, 2)) * depth[:, None]
    points = np.column_stack([lateral, depth])
    state.x = np.concatenate([camera, points.reshape(-1)])
    variances = np.full(len(state.x), POINT_SIGMA_M**2)
    variances[R_SLICE] = POSITION_SIGMA_M**2
    variances[Q_SLICE] = [1e-12, *(3 * [(0.5 * ANGLE_SIGMA_RAD) ** 2])]
    variances[V_SLICE] = variances[W_SLICE] = 0.01
    if uncertain is not None:
        start = CAMERA_SIZE + EUCLIDEAN_SIZE * uncertain
        variances[start : start + 2] = 0.1**2
    state.p = np.diag(variances)
    state.features = [
        FeatureBlock(i, CAMERA_SIZE + EUCLIDEAN_SIZE * i, EUCLIDEAN_SIZE, None, 'new', 0, 0)
        for i in range(FEATURES)
    ]
    return state


def _measurements(
    state: FilterState, rng: np.random.Generator, offsets: dict[int, tuple[float, float]]
) -> dict[int, np.ndarray]:
    """Pixels of the features seen from a camera displaced by about one sigma, with 1 px noise;
    ``offsets`` (px) are added to those features' pixels (wrong matches)."""
    true_camera = state.x[:CAMERA_SIZE].copy()
    true_camera[R_SLICE] += [POSITION_SIGMA_M, -POSITION_SIGMA_M, 0.5 * POSITION_SIGMA_M]
    half = 0.5 * ANGLE_SIGMA_RAD
    true_camera[Q_SLICE] = np.array([1.0, half, -half, 0.0]) / math.sqrt(1.0 + 2 * half**2)
    observed = {}
    for feature in state.features:
        point = state.x[feature.start : feature.start + feature.size]
        pixel = project_feature(CAMERA, true_camera, point, None)[0]
        observed[feature.id] = pixel + rng.normal(0.0, CONFIG.pixel_sigma_px, 2)
        observed[feature.id] += offsets.get(feature.id, (0.0, 0.0))
    return observed


def _sigmas(state: FilterState) -> np.ndarray:
    return np.sqrt(np.diag(state.p))


def test_wrong_matches_inside_the_gate_are_rejected() -> None:
    rng = np.random.default_rng(0)
    prior = _state(rng)
    wrong = {3: (7.0, -4.0), 11: (-6.0, 3.0)}  # inside the gate (~9 px), not consistent
    observed = _measurements(prior, rng, wrong)
    state = copy.deepcopy(prior)
    outcome = ransac_update(state, CAMERA, observed, [], CONFIG, np.random.default_rng(1))
    assert outcome.rejected == [3, 11]
    assert outcome.counts.compatible == FEATURES and outcome.counts.rejected == 2
    assert outcome.counts.low_innovation_inliers + outcome.counts.rescued == FEATURES - 2
    assert all(state.features[i].consecutive_failures == 1 for i in wrong)
    good_only = copy.deepcopy(prior)
    good = {i: pixel for i, pixel in observed.items() if i not in wrong}
    gated_update(good_only, CAMERA, good, [], CONFIG)
    all_gated = copy.deepcopy(prior)
    assert gated_update(all_gated, CAMERA, observed, [], CONFIG).rejected == []
    sigmas = _sigmas(good_only)[:CAMERA_SIZE]
    ransac_error = np.abs(state.x - good_only.x)[:CAMERA_SIZE] / sigmas
    gated_error = np.abs(all_gated.x - good_only.x)[:CAMERA_SIZE] / sigmas
    assert np.max(ransac_error) < 0.05 < np.max(gated_error)
    np.testing.assert_allclose(state.p, good_only.p, atol=1e-3 * np.max(good_only.p))


def test_a_consistent_high_innovation_match_is_rescued() -> None:
    rng = np.random.default_rng(2)
    uncertain = 5
    prior = _state(rng, uncertain)
    start = CAMERA_SIZE + EUCLIDEAN_SIZE * uncertain
    true_point = prior.x[start : start + 3] + np.array([0.12, 0.0, 0.0])  # 1.2 sigma off
    observed = _measurements(prior, rng, {})
    shift = project_feature(CAMERA, prior.x[:CAMERA_SIZE], true_point, None)[0]
    shift -= project_feature(CAMERA, prior.x[:CAMERA_SIZE], prior.x[start : start + 3], None)[0]
    observed[uncertain] = observed[uncertain] + shift
    assert np.linalg.norm(shift) > CONFIG.low_innovation_threshold_px  # just outside
    state = copy.deepcopy(prior)
    outcome = ransac_update(state, CAMERA, observed, [], CONFIG, np.random.default_rng(3))
    assert outcome.rejected == [] and outcome.counts.rescued == 1
    assert outcome.counts.low_innovation_inliers == FEATURES - 1
    moved = state.x[start : start + 3] - prior.x[start : start + 3]
    assert moved[0] > 0.5 * 0.12  # the rescue update pulled the feature towards the truth


def test_the_same_seed_gives_the_same_update() -> None:
    rng = np.random.default_rng(4)
    prior = _state(rng)
    wrong = {i: (rng.uniform(-9.0, 9.0), rng.uniform(-9.0, 9.0)) for i in range(0, 16, 3)}
    observed = _measurements(prior, rng, wrong)
    runs = []
    for _ in range(2):
        state = copy.deepcopy(prior)
        outcome = ransac_update(state, CAMERA, observed, [], CONFIG, np.random.default_rng(5))
        runs.append((state, outcome))
    (first, one), (second, other) = runs
    assert one.counts == other.counts and one.rejected == other.rejected
    assert one.counts.hypotheses > 1
    np.testing.assert_array_equal(first.x, second.x)
    np.testing.assert_array_equal(first.p, second.p)


def test_known_points_take_part_and_count() -> None:
    rng = np.random.default_rng(6)
    prior = _state(rng)
    observed = _measurements(prior, rng, {})
    camera = prior.x[:CAMERA_SIZE]
    points = [np.array([0.2, 0.1, 2.0]), np.array([-0.2, 0.1, 2.0])]
    known = [(p, project_feature(CAMERA, camera, p, None)[0] + [0.0, 25.0]) for p in points]
    outcome = ransac_update(prior, CAMERA, observed, known, CONFIG, np.random.default_rng(7))
    assert outcome.known_used == 0 and outcome.counts.rejected == 2


def _target(prior: FilterState, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """The 4 corners of a 0.3 m square 2.5 m ahead as known points, seen like the features
    (from the displaced camera of ``_measurements``, 1 px noise)."""
    corners = [np.array([x, y, 2.5]) for x, y in ((-0.15, -0.15), (0.15, -0.15), (0.15, 0.15),
                                                    (-0.15, 0.15))]  # fmt: skip
    true_camera = prior.x[:CAMERA_SIZE].copy()
    true_camera[R_SLICE] += [POSITION_SIGMA_M, -POSITION_SIGMA_M, 0.5 * POSITION_SIGMA_M]
    half = 0.5 * ANGLE_SIGMA_RAD
    true_camera[Q_SLICE] = np.array([1.0, half, -half, 0.0]) / math.sqrt(1.0 + 2 * half**2)
    return [
        (c, project_feature(CAMERA, true_camera, c, None)[0] + rng.normal(0.0, 1.0, 2))
        for c in corners
    ]


def test_a_rigid_group_against_the_known_points_loses_to_them() -> None:
    # 15 of 20 features shifted alike by 8 px (a rigid mover in the map, inside their gate):
    # with no known point in view the group outvotes the other 5 and statics are rejected;
    # with the target's 4 corners in view a hypothesis must keep the corners, so no static
    # feature is rejected and the group is (all but one, which the rescue gate lets in).
    # Without the rule the group won here too: corners and statics were all rejected.
    rng = np.random.default_rng(9)
    prior = _state(rng)
    group = set(range(15))
    observed = _measurements(prior, rng, {i: (8.0, 0.0) for i in group})
    known = _target(prior, rng)
    alone = copy.deepcopy(prior)
    outcome = ransac_update(alone, CAMERA, observed, [], CONFIG, np.random.default_rng(10))
    assert set(outcome.rejected) - group  # statics lost to the group
    state = copy.deepcopy(prior)
    outcome = ransac_update(state, CAMERA, observed, known, CONFIG, np.random.default_rng(10))
    assert set(outcome.rejected) <= group and len(outcome.rejected) >= 14
    assert outcome.known_used == 4


def test_gated_mode_keeps_the_gated_update() -> None:
    from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam

    slam = MonoSlam(CAMERA, MonoSlamConfig(update='gated'))
    rng = np.random.default_rng(8)
    slam._state = _state(rng)
    reference = copy.deepcopy(slam._state)
    observed = _measurements(reference, rng, {3: (-6.0, 3.0)})
    outcome = slam._update(observed, np.zeros(0, np.int64), np.zeros((0, 2)))
    expected = gated_update(reference, CAMERA, observed, [], CONFIG)
    assert outcome.rejected == expected.rejected == [] and outcome.counts.hypotheses == 0
    np.testing.assert_array_equal(slam._state.x, reference.x)
    np.testing.assert_array_equal(slam._state.p, reference.p)


@pytest.mark.parametrize(('ratio', 'expected'), [(1.0, 1), (0.9, 2), (0.5, 7), (0.1, 44)])
def test_hypotheses_follow_the_papers_formula(ratio: float, expected: int) -> None:
    assert hypotheses_needed(ratio) == expected


def test_the_update_mode_is_validated() -> None:
    with pytest.raises(ValueError, match=r"update='jcbb': must be one of 'ransac', 'gated'"):
        MonoSlamConfig(update='jcbb')
    with pytest.raises(ValueError, match='ransac_seed'):
        MonoSlamConfig(ransac_seed=-1)


def test_the_batched_gate_is_the_per_match_one() -> None:
    """``gate_all`` decides as S = H P H^T + R match by match does, with a dense covariance
    (camera-feature and feature-feature terms) and known points among the features."""
    rng = np.random.default_rng(5)
    state = _state(rng)
    base = rng.normal(size=(len(state.x), len(state.x)))
    state.p = state.p + 1e-4 * base @ base.T / len(state.x)
    offsets = {k: (rng.uniform(-6, 6), rng.uniform(-6, 6)) for k in range(0, FEATURES, 2)}
    observed = _measurements(state, rng, offsets)
    known = [(np.array([0.3, -0.2, 4.0]), np.array([390.0, 200.0]))]
    all_matches = matches(state, observed, known)
    linearized = linearize_all(state, CAMERA, all_matches)
    decided = gate_all(all_matches, linearized, state.p, CONFIG)
    expected = []
    for match, lin in zip(all_matches, linearized, strict=True):
        assert lin is not None
        s = lin.innovation_covariance(state.p, measurement_variance(match, CONFIG))
        innovation = match.pixel - lin.predicted
        expected.append(float(innovation @ np.linalg.solve(s, innovation)) <= CONFIG.gate)
    assert decided == expected
    assert 0 < sum(decided) < len(decided)  # the offsets put some matches outside


def test_the_preview_is_the_update_where_the_rescue_reads_it() -> None:
    """``previewed`` gives the mean of the update with the low-innovation inliers and its
    covariance over the camera and the judged features, as the full update does, and leaves
    the state as it was."""
    rng = np.random.default_rng(8)
    state = _state(rng)
    base = rng.normal(size=(len(state.x), len(state.x)))
    state.p = state.p + 1e-4 * base @ base.T / len(state.x)
    all_matches = matches(state, _measurements(state, rng, {}), [])
    linearized = linearize_all(state, CAMERA, all_matches, True)
    used = [(m, lin) for m, lin in zip(all_matches[:6], linearized[:6], strict=True) if lin]
    judged = all_matches[6:9]
    before = copy.deepcopy(state)
    preview = previewed(state, used, judged, CONFIG)
    np.testing.assert_array_equal(state.x, before.x)
    np.testing.assert_array_equal(state.p, before.p)
    full = copy.deepcopy(state)
    apply_update(full, used, CONFIG)
    np.testing.assert_allclose(preview.x, full.x, atol=1e-12)
    rows = np.concatenate(
        [np.arange(13)]
        + [
            np.arange(m.feature.start, m.feature.start + m.feature.extent)
            for m in judged
            if m.feature
        ]
    )
    np.testing.assert_allclose(
        preview.p[np.ix_(rows, rows)], full.p[np.ix_(rows, rows)], atol=1e-12, rtol=1e-9
    )


def test_every_update_mode_names_one_update_and_it_is_the_one_used() -> None:
    """The SLAM update is chosen once from MonoSlamConfig.update: each mode has its update,
    and the filter calls the one its config names."""
    from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
    from monoslam_shadow_node.monoslam.core.monoslam_ekf import gated_update
    from monoslam_shadow_node.monoslam.core.monoslam_ransac import ransac_update
    from monoslam_shadow_node.monoslam.core.monoslam_types import UPDATE_MODES
    from monoslam_shadow_node.monoslam.core.monoslam_update import SLAM_UPDATES, slam_update

    assert set(SLAM_UPDATES) == set(UPDATE_MODES)
    assert slam_update('ransac') is ransac_update
    assert slam_update('gated') is not ransac_update and slam_update('gated') is not gated_update
    for mode in UPDATE_MODES:
        filter_ = MonoSlam(CAMERA, MonoSlamConfig(update=mode))
        assert filter_._slam_update is SLAM_UPDATES[mode]
