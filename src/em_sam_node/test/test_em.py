"""EM-SAM: moveable landmarks on a synthetic room, the M-step, the gate, and edge cases."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from synthetic_room import MOVEABLE_IDS, STATIC_IDS, STATIC_POSITIONS, Room, make_room

from em_sam_node.core.assembly import dead_reckoning, select_observations
from em_sam_node.core.em import run_em
from em_sam_node.core.em_types import MODES, EmConfig, EmResult
from em_sam_node.core.em_weights import WEIGHT_MODELS, gate_outliers, weight_model
from slam_core.geometry.se2 import between

SETTINGS = settings(derandomize=True, max_examples=200, deadline=None)


def flagged(result: EmResult) -> list[int]:
    return sorted(result.landmark_ids[result.moveable].tolist())


@pytest.fixture(scope='module')
def room() -> Room:
    return make_room(0)


@pytest.fixture(scope='module')
def robust(room: Room) -> EmResult:
    return run_em(room.data, EmConfig(mode='robust'))


@pytest.fixture(scope='module')
def paper(room: Room) -> EmResult:
    return run_em(room.data, EmConfig(mode='paper'))


# --- the synthetic room ---------------------------------------------------------------------


def test_robust_mode_flags_exactly_the_moved_landmarks(robust: EmResult) -> None:
    assert robust.mode == 'robust'
    assert flagged(robust) == list(MOVEABLE_IDS)
    assert sorted(robust.landmark_ids.tolist()) == sorted(STATIC_IDS + MOVEABLE_IDS)
    static = np.isin(robust.landmark_ids, STATIC_IDS)
    assert np.all(robust.weights[static] > 0.9)
    assert np.all(robust.weights[~static] < 0.1)
    assert robust.converged


def test_robust_mode_recovers_the_trajectory_and_the_static_map(
    room: Room, robust: EmResult
) -> None:
    truth = room.true_poses
    odometry_error = np.abs(dead_reckoning(room.data)[:, :2] - truth[:, :2]).max()
    error = np.abs(robust.poses[:, :2] - truth[:, :2]).max()
    assert error < 0.15 and error < 0.5 * odometry_error
    position_errors_m = np.linalg.norm(robust.poses[:, :2] - truth[:, :2], axis=1)
    assert np.sqrt(np.mean(position_errors_m**2)) < 0.08
    static = np.isin(robust.landmark_ids, STATIC_IDS)
    order = robust.landmark_ids[static]
    np.testing.assert_allclose(robust.positions[static], STATIC_POSITIONS[order], atol=0.15)


def test_robust_mode_places_a_moved_landmark_at_its_latest_sighting(robust: EmResult) -> None:
    index = int(np.flatnonzero(robust.landmark_ids == 100)[0])
    sightings = robust.sightings[100]
    np.testing.assert_array_equal(robust.positions[index], sightings.positions[0])
    np.testing.assert_allclose(sightings.positions[0], [3.0, 3.0], atol=0.2)
    np.testing.assert_allclose(sightings.positions[-1], [3.0, 0.0], atol=0.2)


def test_paper_mode_reports_weights_and_their_history(room: Room, paper: EmResult) -> None:
    assert paper.mode == 'paper'
    count = len(paper.landmark_ids)
    assert np.all((paper.weights >= 0.0) & (paper.weights <= 1.0))
    assert paper.weight_history.shape == (paper.em_iterations + 1, count)
    np.testing.assert_array_equal(paper.weight_history[0], np.ones(count))
    np.testing.assert_array_equal(paper.weight_history[-1], paper.weights)
    assert np.all((paper.weight_history >= 0.0) & (paper.weight_history <= 1.0))
    np.testing.assert_array_equal(paper.moveable, paper.weights < 0.5)
    assert paper.poses.shape == room.true_poses.shape
    assert not paper.gated.any()  # the paper has no gate


def test_sightings_are_most_recent_first_with_symmetric_psd_covariances(
    room: Room, robust: EmResult
) -> None:
    data = room.data
    assert set(robust.sightings) == set(MOVEABLE_IDS)
    for landmark_id, sightings in robust.sightings.items():
        expected = np.sort(data.obs_stamp_ns[data.obs_landmark_id == landmark_id])[::-1]
        np.testing.assert_array_equal(sightings.stamps_ns, expected)
        covariances = sightings.covariances
        np.testing.assert_array_equal(covariances, np.swapaxes(covariances, 1, 2))
        assert np.all(np.linalg.eigvalsh(covariances) >= 0.0)


# --- M-step and gate ------------------------------------------------------------------------


@SETTINGS
@given(
    mode=st.sampled_from(('paper', 'robust')),
    lagrange_lambda=st.floats(1e-3, 1e4),
    rows=st.lists(
        st.tuples(
            st.integers(0, 5),
            st.floats(0.0, 1e9, allow_nan=False, allow_infinity=False),
            st.booleans(),
        ),
        min_size=0,
        max_size=60,
    ),
)
def test_m_step_weights_are_always_in_zero_one(
    mode: str, lagrange_lambda: float, rows: list[tuple[int, float, bool]]
) -> None:
    config = EmConfig(mode=mode, lagrange_lambda=lagrange_lambda)
    landmarks = np.array([r[0] for r in rows], dtype=np.int64)
    mahalanobis = np.array([r[1] for r in rows], dtype=float)
    included = np.array([r[2] for r in rows], dtype=bool)
    weights = weight_model(config).m_step(mahalanobis, landmarks, 6, included)
    assert weights.shape == (6,)
    assert np.all((weights >= 0.0) & (weights <= 1.0))


def test_m_step_paper_mode_is_eq_14() -> None:
    config = EmConfig(mode='paper', lagrange_lambda=10.0)
    mahalanobis = np.array([1.0, 3.0, 8.0, 30.0])
    weights = weight_model(config).m_step(
        mahalanobis, np.array([0, 0, 1, 2]), 3, np.ones(4, dtype=bool)
    )
    np.testing.assert_allclose(weights, [1.0 - 4.0 / 20.0, 1.0 - 8.0 / 20.0, 0.0])


def test_m_step_robust_mode_keeps_a_consistent_landmark_and_drops_a_moved_one() -> None:
    config = EmConfig(mode='robust')
    count = 40
    # A static landmark's sum stays below its dof 2n - 2 = 78; a moved one's is far above.
    static = np.full(count, 1.5)
    moved = static + 25.0
    landmarks = np.repeat([0, 1], count)
    weights = weight_model(config).m_step(
        np.concatenate([static, moved]), landmarks, 2, np.ones(2 * count, dtype=bool)
    )
    assert weights[0] == 1.0 and weights[1] == 0.0


def test_a_landmark_seen_once_keeps_weight_one_in_robust_mode() -> None:
    weights = weight_model(EmConfig(mode='robust')).m_step(
        np.array([1e6, 0.5, 0.7]),
        np.array([0, 1, 1]),
        2,
        np.ones(3, dtype=bool),
    )
    assert weights[0] == 1.0
    paper = weight_model(EmConfig(mode='paper')).m_step(
        np.array([1e6]), np.array([0]), 1, np.ones(1, bool)
    )
    assert paper[0] == 0.0  # the paper's eq. 14 has no such rule


def test_a_landmark_seen_once_in_the_room_keeps_weight_one(room: Room) -> None:
    data = room.data
    pose_index = 10
    extra = dataclasses.replace(
        data,
        obs_keyframe=np.append(data.obs_keyframe, pose_index),
        obs_landmark_id=np.append(data.obs_landmark_id, 55),
        obs_z=np.vstack([data.obs_z, [[2.5, 0.4]]]),
        obs_cov=np.concatenate([data.obs_cov, data.obs_cov[:1]]),
    )
    result = run_em(extra, EmConfig(mode='robust'))
    index = int(np.flatnonzero(result.landmark_ids == 55)[0])
    assert result.weights[index] == 1.0 and not result.moveable[index]
    assert result.num_observations[index] == 1


def test_gate_outliers_gates_an_isolated_outlier_but_not_a_disagreeing_landmark() -> None:
    config = EmConfig(mode='robust', max_gated_fraction=0.1)
    count = 20
    landmarks = np.repeat([0, 1], count)
    mahalanobis = np.full(2 * count, 1.5)
    mahalanobis[3] = 400.0  # landmark 0: one gross outlier
    mahalanobis[count : count + 12] += np.linspace(100.0, 200.0, 12)  # landmark 1: moved
    gated = gate_outliers(config, mahalanobis, landmarks, 2)
    assert np.flatnonzero(gated[:count]).tolist() == [3]
    # Landmark 1: only floor(0.1 * 20) = 2 of its 12 large sightings, the largest ones.
    assert np.flatnonzero(gated[count:]).tolist() == [10, 11]
    weights = weight_model(config).m_step(mahalanobis, landmarks, 2, ~gated)
    assert weights[0] == 1.0 and weights[1] == 0.0


def test_gate_outliers_needs_enough_sightings_to_gate_any() -> None:
    config = EmConfig(mode='robust', max_gated_fraction=0.1)
    mahalanobis = np.array([500.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])  # 9 sightings
    gated = gate_outliers(config, mahalanobis, np.zeros(9, dtype=np.int64), 1)
    assert not gated.any()


def test_a_gross_outlier_sighting_is_gated_not_a_moved_landmark(room: Room) -> None:
    data = room.data
    row = int(np.flatnonzero(data.obs_landmark_id == 3)[5])
    z = data.obs_z.copy()
    z[row, 0] += 2.0  # one sighting 2 m too far: ~67 sigma
    result = run_em(dataclasses.replace(data, obs_z=z), EmConfig(mode='robust'))
    assert result.gated[row]
    assert result.gated.sum() <= 2 * 3 + 1  # the moved landmarks' few, and this one
    assert flagged(result) == list(MOVEABLE_IDS)
    assert np.abs(result.poses[:, :2] - room.true_poses[:, :2]).max() < 0.15


# --- structure and edge cases ---------------------------------------------------------------


@pytest.mark.parametrize('mode', ['robust', 'paper'])
def test_all_landmarks_moveable_leaves_the_odometry_trajectory(mode: str) -> None:
    data = make_room(0, with_static=False).data
    assert set(data.obs_landmark_id.tolist()) == set(MOVEABLE_IDS)
    result = run_em(data, EmConfig(mode=mode))
    assert flagged(result) == list(MOVEABLE_IDS)
    np.testing.assert_allclose(result.poses, dead_reckoning(data), atol=1e-12)
    assert set(result.sightings) == set(MOVEABLE_IDS)


@pytest.mark.parametrize('mode', ['robust', 'paper'])
def test_a_graph_in_two_pieces_solves_and_reports_two_pieces(mode: str) -> None:
    room = make_room(0, moving=False)
    data = room.data
    split = 36  # the end of the first loop: no odometry from keyframe 36 to 37
    keep_odometry = data.odometry_from != split
    ids = np.where(data.obs_keyframe > split, data.obs_landmark_id + 10, data.obs_landmark_id)
    pieces = dataclasses.replace(
        data,
        odometry_from=data.odometry_from[keep_odometry],
        odometry_to=data.odometry_to[keep_odometry],
        odometry_u=data.odometry_u[keep_odometry],
        odometry_cov=data.odometry_cov[keep_odometry],
        obs_landmark_id=ids,
    )
    pieces = select_observations(pieces, np.isin(data.obs_landmark_id, STATIC_IDS))
    result = run_em(pieces, EmConfig(mode=mode))
    assert result.num_pieces == 2
    assert np.all(np.isfinite(result.poses)) and np.all(np.isfinite(result.positions))
    if mode == 'paper':
        return  # its one lambda flags static landmarks too: only robust mode is accurate
    truth = room.true_poses
    np.testing.assert_allclose(result.poses[: split + 1, :2], truth[: split + 1, :2], atol=0.15)
    # The second piece keeps its shape (where it sits is free).
    shape = between(np.repeat(result.poses[split + 1 :][:1], 36, 0), result.poses[split + 1 :])
    true_shape = between(np.repeat(truth[split + 1 :][:1], 36, 0), truth[split + 1 :])
    np.testing.assert_allclose(shape[:, :2], true_shape[:, :2], atol=0.15)


def test_empty_data_gives_an_odometry_only_result() -> None:
    data = select_observations(make_room(0).data, np.zeros(0, dtype=np.int64))
    for mode in ('robust', 'paper'):
        result = run_em(data, EmConfig(mode=mode))
        np.testing.assert_allclose(result.poses, dead_reckoning(data))
        assert result.landmark_ids.shape == (0,) and result.weights.shape == (0,)
        assert result.positions.shape == (0, 2) and result.covariances.shape == (0, 2, 2)
        assert result.weight_history.shape == (1, 0)
        assert result.sightings == {} and result.num_pieces == 1 and result.converged


@pytest.mark.parametrize(
    ('setting', 'value'),
    [
        ('lagrange_lambda', 0.0),
        ('lagrange_lambda', -5.0),
        ('lagrange_lambda', math.nan),
        ('lagrange_lambda', math.inf),
        ('mode', 'fancy'),
        ('moveable_threshold', 1.0),
        ('false_alarm_probability', 0.0),
        ('max_gated_fraction', 1.0),
        ('seed_kernel', 'tukey'),
        ('max_noise_scale', 0.5),
        ('model_error_m', -0.1),
        ('model_error_m', math.nan),
        ('final_kernel', 'tukey'),
        ('final_kernel_scale', 0.0),
    ],
)
def test_em_config_rejects_bad_settings_naming_them(setting: str, value: object) -> None:
    with pytest.raises(ValueError, match=f'EM-SAM setting {setting}='):
        EmConfig(**{setting: value})  # type: ignore[arg-type]


def test_noise_scales_are_per_component_medians_over_their_chi_square_expectation() -> None:
    from em_sam_node.core.em_weights import observation_noise_scales

    rng = np.random.default_rng(3)
    sigma = np.array([0.1, 0.01])  # modelled range (m) and bearing (rad) sigmas
    cov = np.tile(np.diag(sigma**2), (20000, 1, 1))
    # Ranges twice as noisy as modelled, bearings as modelled.
    innovations = rng.normal(0.0, 1.0, (20000, 2)) * sigma * np.array([2.0, 1.0])
    np.testing.assert_allclose(observation_noise_scales(innovations, cov), [4.0, 1.0], rtol=0.05)
    # Never below 1: a model looser than the data is kept.
    assert observation_noise_scales(0.5 * innovations, cov)[1] == 1.0
    np.testing.assert_array_equal(observation_noise_scales(np.zeros((0, 2)), cov[:0]), [1, 1])


def test_with_noise_scales_scales_variances_and_the_correlation_consistently(room: Room) -> None:
    from em_sam_node.core.em_weights import with_noise_scales

    data = dataclasses.replace(room.data, obs_cov=room.data.obs_cov.copy())
    data.obs_cov[:, 0, 1] = data.obs_cov[:, 1, 0] = 1e-5
    scaled = with_noise_scales(data, np.array([4.0, 9.0]))
    np.testing.assert_allclose(scaled.obs_cov[:, 0, 0], 4.0 * data.obs_cov[:, 0, 0])
    np.testing.assert_allclose(scaled.obs_cov[:, 1, 1], 9.0 * data.obs_cov[:, 1, 1])
    np.testing.assert_allclose(scaled.obs_cov[:, 0, 1], 6.0 * data.obs_cov[:, 0, 1])
    assert data.obs_cov[0, 0, 0] == room.data.obs_cov[0, 0, 0]  # the input is not modified


def test_robust_mode_estimates_a_range_noise_wider_than_modelled(room: Room) -> None:
    """Ranges 3x noisier than the model: the factors find it, and nothing static is flagged."""
    rng = np.random.default_rng(11)
    z = room.data.obs_z.copy()
    sigma_r = np.sqrt(room.data.obs_cov[:, 0, 0])
    z[:, 0] += rng.normal(0.0, 1.0, len(z)) * np.sqrt(8.0) * sigma_r  # total 3 sigma
    noisy = dataclasses.replace(room.data, obs_z=z)
    result = run_em(noisy, EmConfig(mode='robust'), record_snapshots=False)
    assert 5.0 < result.noise_scale[0] < 12.0
    assert result.noise_scale[1] < 1.5
    assert 5.0 < result.final_noise_scale[0] < 12.0
    assert flagged(result) == list(MOVEABLE_IDS)
    off = run_em(
        noisy, EmConfig(mode='robust', estimate_noise_scale=False), record_snapshots=False
    )
    np.testing.assert_array_equal(off.noise_scale, [1.0, 1.0])
    np.testing.assert_array_equal(off.final_noise_scale, [1.0, 1.0])


def test_model_error_widens_the_test_covariance_by_a_position_error() -> None:

    cov = np.repeat(np.diag([0.01, 0.0001])[None], 2, axis=0)
    z = np.array([[2.0, 0.1], [4.0, -0.3]])
    widened = weight_model(EmConfig(mode='robust', model_error_m=0.2)).test_covariances(cov, z)
    assert widened is not None
    np.testing.assert_allclose(widened[:, 0, 0], 0.01 + 0.04)
    np.testing.assert_allclose(widened[:, 1, 1], 0.0001 + (0.2 / z[:, 0]) ** 2)
    assert weight_model(EmConfig(mode='paper')).test_covariances(cov, z) is None
    assert (
        weight_model(EmConfig(mode='robust', model_error_m=0.0)).test_covariances(cov, z) is None
    )


def test_every_mode_names_one_weight_model() -> None:
    """EmConfig's modes and the weight models are the same set, each chosen by its name."""
    assert set(WEIGHT_MODELS) == set(MODES)
    for mode in MODES:
        assert type(weight_model(EmConfig(mode=mode))) is WEIGHT_MODELS[mode]
