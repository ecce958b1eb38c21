"""The robust first E-step (core.seeding): relocalization and independence of the chunking."""

from __future__ import annotations

import numpy as np
import pytest

from em_sam_node.core.em import _solve
from em_sam_node.core.em_types import SEED_KERNELS, EmConfig
from em_sam_node.core.problem import Estimate, SlamProblem
from em_sam_node.core.seeding import Correction, incremental_seed, relocalization
from em_sam_node.offline import read_ground_truth, replay_bag
from slam_evaluation.em_sam_metrics import ate_rmse
from slam_sim.core.office import simulate_office
from slam_sim.office_bag import write_office_bag

RNG_SEED = 11


def mapped_square() -> dict[int, np.ndarray]:
    """Eight landmarks on the walls of a 4 m room."""
    return {
        i: np.array(p, dtype=float)
        for i, p in enumerate([(0, 1), (0, 3), (1, 4), (3, 4), (4, 3), (4, 1), (3, 0), (1, 0)])
    }


def sightings(
    landmarks: dict[int, np.ndarray], drift: Correction, per_landmark: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy sightings of every landmark as seen through poses off by ``drift``'s inverse."""
    rng = np.random.default_rng(RNG_SEED)
    ids = np.repeat(np.array(sorted(landmarks)), per_landmark)
    truth = np.array([landmarks[i] for i in ids.tolist()])
    c, s = np.cos(-drift.angle), np.sin(-drift.angle)
    inverse = (truth - drift.translation) @ np.array([[c, -s], [s, c]]).T
    return inverse + rng.normal(0.0, 0.02, inverse.shape), ids


def relocalize(points: np.ndarray, ids: np.ndarray, landmarks: dict[int, np.ndarray]):
    poses = np.column_stack([points, np.zeros(len(points))])
    return relocalization(
        points, ids, landmarks, 0.25, poses=poses, max_shift_m=2.0, max_angle=0.3
    )


def test_relocalization_recovers_a_drift_of_a_metre_and_five_degrees() -> None:
    landmarks = mapped_square()
    drift = Correction(np.radians(5.0), np.array([0.8, -0.6]))
    points, ids = sightings(landmarks, drift)
    found = relocalize(points, ids, landmarks)
    assert found is not None
    assert found.angle == pytest.approx(drift.angle, abs=0.01)
    np.testing.assert_allclose(found.translation, drift.translation, atol=0.03)


def test_relocalization_follows_the_static_majority_not_the_moved_landmarks() -> None:
    landmarks = mapped_square()
    drift = Correction(np.radians(-3.0), np.array([-0.5, 0.4]))
    points, ids = sightings(landmarks, drift)
    rng = np.random.default_rng(RNG_SEED + 1)
    for moved in (1, 4, 6):  # three landmarks moved independently by 1-2 m
        points[ids == moved] += rng.uniform(1.0, 2.0, 2) * rng.choice([-1, 1], 2)
    found = relocalize(points, ids, landmarks)
    assert found is not None
    assert found.angle == pytest.approx(drift.angle, abs=0.01)
    np.testing.assert_allclose(found.translation, drift.translation, atol=0.05)


def test_relocalization_keeps_the_poses_when_they_already_agree_with_the_map() -> None:
    landmarks = mapped_square()
    points, ids = sightings(landmarks, Correction(0.0, np.zeros(2)))
    assert relocalize(points, ids, landmarks) is None


def test_relocalization_rejects_an_implausibly_large_correction() -> None:
    landmarks = mapped_square()
    points, ids = sightings(landmarks, Correction(np.radians(40.0), np.array([0.0, 0.0])))
    assert relocalize(points, ids, landmarks) is None  # more than max_angle


def test_relocalization_needs_two_mapped_landmarks() -> None:
    landmarks = mapped_square()
    points, ids = sightings(landmarks, Correction(0.1, np.array([0.5, 0.5])))
    one = ids == 0
    assert relocalize(points[one], ids[one], landmarks) is None
    unknown = relocalize(points, ids + 100, landmarks)
    assert unknown is None


@pytest.mark.replay
@pytest.mark.parametrize('chunk_s', [17.0, 20.0, 23.0])
def test_the_seed_closes_the_corridor_loop_whatever_the_chunking(
    tmp_path_factory: pytest.TempPathFactory, chunk_s: float
) -> None:
    """Before relocalization, chunk boundaries 1-5 s off the default left a 1 m error."""
    path = tmp_path_factory.getbasetemp() / 'office_seed_phase'
    if not path.exists():
        write_office_bag(simulate_office(7, 'standard'), path)
    data = replay_bag(path).data
    truth = read_ground_truth(path).poses_at(data.keyframe_stamps_ns)
    config = EmConfig(mode='robust')
    kernel = SEED_KERNELS[config.seed_kernel](config.seed_kernel_scale)

    def robust_solve(problem: SlamProblem, start: Estimate) -> Estimate:
        return _solve(config, problem, start, robust_kernel=kernel)

    poses, _ = incremental_seed(data, robust_solve, chunk_s=chunk_s)
    np.testing.assert_allclose(poses[0], data.prior_pose, atol=1e-9)
    assert ate_rmse(poses[:, :2], truth[:, :2]) < 0.15
