"""core.odometry_calibration: translation and rotation scales of the odometry, estimated
with the trajectory."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_continuation import HEADING_BIAS_RAD, ODOMETRY_SIGMA, corridor_loop
from test_seeding import rms_error

from em_sam_node.core.assembly import MappingData
from em_sam_node.core.em import run_em
from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.odometry_calibration import OdometryCalibration, estimate_calibration

# The UTIAS MRCLAM robots' odometry reports 4-9 % more translation and 3-12 % more rotation
# than Vicon measured; these are in that range.
TRANSLATION_ERROR = 1.07
ROTATION_ERROR = 1.10


def unbiased_corridor(seed: int) -> tuple[MappingData, np.ndarray]:
    """The corridor loop of test_seeding without its heading bias (a drift per step that
    no scale describes): odometry with white noise only."""
    data, truth = corridor_loop(seed)
    u = data.odometry_u.copy()
    u[:, 2] -= HEADING_BIAS_RAD
    return dataclasses.replace(data, odometry_u=u), truth


def miscalibrated(data: MappingData) -> MappingData:
    """``data`` with every increment's translation and turn overstated."""
    scale = np.array([TRANSLATION_ERROR, TRANSLATION_ERROR, ROTATION_ERROR])
    return dataclasses.replace(data, odometry_u=data.odometry_u * scale)


def test_the_scales_that_explain_the_true_trajectory_are_recovered() -> None:
    data, truth = unbiased_corridor(0)
    found = estimate_calibration(miscalibrated(data), truth)
    # Within three standard deviations of the least-squares estimate: the turn noise over
    # the summed squared turns (8 corners), the forward noise over the summed squared steps.
    u = miscalibrated(data).odometry_u
    rotation_sigma = ODOMETRY_SIGMA[2] / np.sqrt(np.sum(u[:, 2] ** 2))
    translation_sigma = ODOMETRY_SIGMA[0] / np.sqrt(np.sum(u[:, 0] ** 2))
    assert found.translation == pytest.approx(1 / TRANSLATION_ERROR, abs=3 * translation_sigma)
    assert found.rotation == pytest.approx(1 / ROTATION_ERROR, abs=3 * rotation_sigma)


def test_noise_free_increments_give_the_exact_inverse() -> None:
    data, truth = corridor_loop(0)
    """Up to the prior's pull (its information is tiny next to 77 exact increments)."""
    data, truth = corridor_loop(0)
    exact = dataclasses.replace(data, odometry_u=_true_increments(data, truth))
    found = estimate_calibration(miscalibrated(exact), truth)
    assert found.translation == pytest.approx(1 / TRANSLATION_ERROR, rel=1e-3)
    assert found.rotation == pytest.approx(1 / ROTATION_ERROR, rel=1e-3)


def _true_increments(data: MappingData, truth: np.ndarray) -> np.ndarray:
    from em_sam_node.core.factors import odometry_error

    zero = np.zeros_like(data.odometry_u)
    return -odometry_error(truth[data.odometry_from], truth[data.odometry_to], zero)


def test_applying_scales_the_increments_and_their_covariances() -> None:
    data, _ = corridor_loop(0)
    calibration = OdometryCalibration(0.9, 0.8)
    applied = calibration.apply(data)
    np.testing.assert_allclose(applied.odometry_u, data.odometry_u * [0.9, 0.9, 0.8])
    scale = np.diag([0.9, 0.9, 0.8])
    np.testing.assert_allclose(applied.odometry_cov[3], scale @ data.odometry_cov[3] @ scale)
    assert OdometryCalibration().apply(data) is data


def test_a_robot_that_never_moved_keeps_the_identity() -> None:
    data, truth = corridor_loop(0)
    still = dataclasses.replace(data, odometry_u=np.zeros_like(data.odometry_u))
    assert estimate_calibration(still, np.repeat(truth[:1], len(truth), 0)).is_identity


def test_the_robust_mode_calibrates_the_odometry_and_keeps_its_accuracy() -> None:
    """Odometry overstating motion by 7 % and 10 %: the robust mode reports the inverse
    scales, and its trajectory is as good as on the calibrated odometry; without the
    calibration it is worse."""
    data, truth = unbiased_corridor(2)
    reference = run_em(data, EmConfig(mode='robust'), record_snapshots=False)
    biased = miscalibrated(data)
    result = run_em(biased, EmConfig(mode='robust'), record_snapshots=False)
    translation, rotation = result.odometry_calibration
    reference_translation, reference_rotation = reference.odometry_calibration
    assert translation * TRANSLATION_ERROR == pytest.approx(reference_translation, rel=0.01)
    assert rotation * ROTATION_ERROR == pytest.approx(reference_rotation, rel=0.01)
    assert not result.moveable.any()
    assert rms_error(result.poses, truth) < rms_error(reference.poses, truth) + 0.02
    uncalibrated = run_em(
        biased, EmConfig(mode='robust', calibrate_odometry=False), record_snapshots=False
    )
    assert uncalibrated.odometry_calibration == (1.0, 1.0)
    # Overstated by 7 % and 10 % and not calibrated, the trajectory is off by metres.
    assert rms_error(uncalibrated.poses, truth) > 3 * rms_error(result.poses, truth)
