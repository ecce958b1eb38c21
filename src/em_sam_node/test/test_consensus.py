"""core.consensus: telling a drifted stretch (most landmarks agree on one correction) from
landmarks that moved (each its own way)."""

from __future__ import annotations

import numpy as np
import pytest

from em_sam_node.core.consensus import MIN_CONSENSUS, Correction, consensus, fit_rigid

RNG_SEED = 11
NOISE_M = 0.02
LEVEL = 1e-3  # the test's false alarm probability


def mapped_square() -> np.ndarray:
    """Eight landmarks on the walls of a 4 m room (8,2)."""
    return np.array([(0, 1), (0, 3), (1, 4), (3, 4), (4, 3), (4, 1), (3, 0), (1, 0)], float)


def seen_through(mapped: np.ndarray, drift: Correction, seed: int = RNG_SEED) -> np.ndarray:
    """Where each landmark appears through a trajectory off by ``drift``'s inverse."""
    rng = np.random.default_rng(seed)
    c, s = np.cos(-drift.angle), np.sin(-drift.angle)
    inverse = (mapped - drift.translation) @ np.array([[c, -s], [s, c]]).T
    return inverse + rng.normal(0.0, NOISE_M, inverse.shape)


def agree(seen: np.ndarray, mapped: np.ndarray) -> tuple[Correction, np.ndarray]:
    return consensus(seen, mapped, np.full(len(seen), NOISE_M), LEVEL)


def test_fit_rigid_inverts_a_known_motion() -> None:
    mapped = mapped_square()
    motion = Correction(0.3, np.array([1.0, -2.0]))
    found = fit_rigid(mapped, motion.apply_points(mapped))
    assert found.angle == pytest.approx(0.3, abs=1e-12)
    np.testing.assert_allclose(found.translation, [1.0, -2.0], atol=1e-12)


def test_a_drift_of_a_metre_and_five_degrees_is_recovered_by_all_landmarks() -> None:
    mapped = mapped_square()
    drift = Correction(np.radians(5.0), np.array([0.8, -0.6]))
    found, mask = agree(seen_through(mapped, drift), mapped)
    assert mask.all()
    assert found.angle == pytest.approx(drift.angle, abs=0.01)
    np.testing.assert_allclose(found.translation, drift.translation, atol=0.03)


def test_the_static_majority_wins_over_landmarks_that_moved_their_own_ways() -> None:
    mapped = mapped_square()
    drift = Correction(np.radians(-3.0), np.array([-0.5, 0.4]))
    seen = seen_through(mapped, drift)
    rng = np.random.default_rng(RNG_SEED + 1)
    moved = [1, 4, 6]
    for index in moved:  # moved independently by 1-2 m
        seen[index] += rng.uniform(1.0, 2.0, 2) * rng.choice([-1, 1], 2)
    found, mask = agree(seen, mapped)
    assert np.flatnonzero(~mask).tolist() == moved
    assert found.angle == pytest.approx(drift.angle, abs=0.01)
    np.testing.assert_allclose(found.translation, drift.translation, atol=0.05)


def test_no_drift_is_the_identity_with_everyone_agreeing() -> None:
    mapped = mapped_square()
    found, mask = agree(seen_through(mapped, Correction(0.0, np.zeros(2))), mapped)
    assert mask.all()
    assert found.angle == 0.0
    np.testing.assert_array_equal(found.translation, [0.0, 0.0])


def test_a_minority_that_moved_together_is_not_a_drift() -> None:
    """Three of eight landmarks carried together (a desk) agree on one motion, but the five
    that did not move outvote them: the identity, and the three are outside it."""
    mapped = mapped_square()
    seen = seen_through(mapped, Correction(0.0, np.zeros(2)))
    seen[[2, 3, 4]] += np.array([1.5, -1.0])
    found, mask = agree(seen, mapped)
    assert found.angle == 0.0
    assert np.flatnonzero(~mask).tolist() == [2, 3, 4]


def test_without_a_majority_nothing_agrees() -> None:
    """Four landmarks, two pairs shifted two different ways: no correction has more than
    half of them, so there is no consensus (the seed then tests each on its own)."""
    mapped = mapped_square()[:4]
    seen = seen_through(mapped, Correction(0.0, np.zeros(2)))
    seen[[0, 1]] += np.array([1.0, 0.0])
    seen[[2, 3]] += np.array([0.0, -1.5])
    found, mask = agree(seen, mapped)
    assert not mask.any()
    assert found.angle == 0.0


def test_the_odometry_as_it_is_comes_before_a_compromise() -> None:
    """Five landmarks where they were mapped and four carried 0.4 m together. A correction
    halfway (0.2 m) would bring all nine within their tolerance (0.37 m at sigmas of
    0.1 m); the odometry as it is, which the five agree on, comes first, and the four are
    outside it."""
    mapped = np.vstack([mapped_square(), [[2.0, 2.0]]])
    seen = seen_through(mapped, Correction(0.0, np.zeros(2)))
    carried = [5, 6, 7, 8]
    seen[carried] += np.array([0.4, 0.0])
    found, mask = consensus(seen, mapped, np.full(len(seen), 0.1), LEVEL)
    assert found.angle == 0.0
    np.testing.assert_array_equal(found.translation, [0.0, 0.0])
    assert np.flatnonzero(~mask).tolist() == carried


def test_fewer_landmarks_than_a_consensus_needs_give_none() -> None:
    mapped = mapped_square()[: MIN_CONSENSUS - 1]
    found, mask = agree(seen_through(mapped, Correction(0.1, np.array([0.5, 0.5]))), mapped)
    assert not mask.any()
    assert found.angle == 0.0
