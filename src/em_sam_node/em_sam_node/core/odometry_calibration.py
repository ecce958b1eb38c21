"""Odometry scale calibration (translation, rotation), estimated with the trajectory as an
M-step parameter; see docs/design/em_sam_core.md."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from em_sam_node.core.assembly import MappingData
from em_sam_node.core.factors import odometry_error
from slam_core.arrays import FloatArray

NOMINAL = np.array([1.0, 1.0])  # translation scale, rotation scale
# Wheel radius and track width known to 10 % (MRCLAM's odometry is 3-12 % off).
PRIOR_SCALE_SIGMA = 0.1


@dataclass(frozen=True)
class OdometryCalibration:
    """Scales of every increment: u0, u1 times ``translation``, u2 times ``rotation``."""

    translation: float = 1.0
    rotation: float = 1.0

    @property
    def is_identity(self) -> bool:
        """Whether this is the nominal odometry."""
        return bool(np.array_equal(self.parameters, NOMINAL))

    @property
    def parameters(self) -> FloatArray:
        """(translation, rotation) as an array (2,)."""
        return np.array([self.translation, self.rotation])

    def apply(self, data: MappingData) -> MappingData:
        """Return ``data`` with its odometry increments and covariances calibrated."""
        if self.is_identity:
            return data
        scale = np.array([self.translation, self.translation, self.rotation])
        return dataclasses.replace(
            data,
            odometry_u=data.odometry_u * scale,
            odometry_cov=data.odometry_cov * scale[:, None] * scale[None, :],
        )


def estimate_calibration(data: MappingData, poses: FloatArray) -> OdometryCalibration:
    """The MAP scales (from the raw odometry of ``data``) that best explain ``poses`` (N, 3)."""
    prior_information = np.eye(2) / PRIOR_SCALE_SIGMA**2
    if len(data.odometry_u) == 0:
        return OdometryCalibration()
    u = data.odometry_u
    shown = u - odometry_error(poses[data.odometry_from], poses[data.odometry_to], u)
    information = np.linalg.inv(data.odometry_cov)
    design = np.zeros((len(u), 3, 2))  # S u = design @ (translation, rotation)
    design[:, 0, 0] = u[:, 0]
    design[:, 1, 0] = u[:, 1]
    design[:, 2, 1] = u[:, 2]
    weighted = np.einsum('mji,mjk->mik', design, information)  # A^T C^-1
    normal = np.einsum('mik,mkl->il', weighted, design) + prior_information
    rhs = np.einsum('mik,mk->i', weighted, shown) + prior_information @ NOMINAL
    parameters = np.linalg.solve(normal, rhs)
    if not np.all(np.isfinite(parameters)) or min(parameters[0], parameters[1]) <= 0:
        return OdometryCalibration()
    return OdometryCalibration(*(float(p) for p in parameters))
