"""Odometry scale calibration, estimated with the trajectory (an M-step parameter).

Wheel odometry has systematic errors that no per-increment covariance carries: a wheel
radius or a track width off by a few percent scales every translation or every turn by the
same factor, so the dead-reckoned drift grows with the distance and the angle travelled
instead of their square root. On the UTIAS MRCLAM runs the odometry reports 4-9 % more
translation and 3-12 % more rotation than Vicon measured, robot by robot. Against such
odometry a static landmark re-seen after a long stretch looks moved, and fitting it bends
the trajectory against increments whose covariance has no room for the bend.

The calibration is a translation scale and a rotation scale applied to every increment
(Kummerle, Grisetti, Stachniss, Burgard, "Simultaneous calibration, localization, and
mapping", IROS 2011, with the drive's kinematic parameters reduced to these two). Given
the trajectory, the odometry error is linear in them, so their maximum a-posteriori values
are a 2x2 weighted least-squares solve over the increments, each weighted by its
information matrix, with a prior at the nominal odometry (scales known to
``PRIOR_SCALE_SIGMA``). The prior matters while the robot has only driven straight: the
rotation scale is then unobservable. Alternated with the trajectory solve (an M-step next
to the landmark weights), every step lowers the same joint cost.

A third parameter, a heading drift per metre (wheels of unequal radii), was tried and left
out: on windows of a few minutes it traded off against the rotation scale and settled on
the wrong sign (MRCLAM data set 6, robot 4, first 600 s), locking in a wrong trajectory.

Without landmarks the trajectory follows the odometry it was given and the parameters stay
where they are: a run that cannot observe its calibration keeps the identity.
"""

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
    """Applied to every increment u: u0 and u1 times ``translation``, u2 times
    ``rotation``; the covariance S C S with S = diag(translation, translation, rotation)."""

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
    """The parameters (from the raw odometry of ``data``) that best explain ``poses`` (N,3).

    Minimizes sum_m (S u_m - g_m)^T C_m^-1 (S u_m - g_m) plus the prior over the two
    scales, where g_m is the increment the trajectory shows between the keyframes of
    increment m in the odometry's own terms (forward, sideways, turn) and C_m the
    increment's covariance.
    """
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
