"""A tag whose pose another detector estimated (apriltag_ros), given marker_detector's quality
gates and pose covariance. Design notes: docs/design/marker_core.md"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from marker_detector.core.detection import MarkerDetection, Rejection
from marker_detector.core.detector_config import DetectorConfig
from marker_detector.core.edges import side_lengths
from marker_detector.core.pose import corner_jacobian, marker_object_points, pose_covariance
from slam_core.camera import CameraModel
from slam_core.params import field_rule

_DETECTOR = DetectorConfig()


@dataclass(frozen=True)
class TagGates:
    """The quality gates and the corner noise: DetectorConfig's fields, defaults and rules."""

    min_side_px: float = _DETECTOR.min_side_px
    max_reprojection_error_px: float = _DETECTOR.max_reprojection_error_px
    max_range_m: float = _DETECTOR.max_range_m
    max_viewing_angle_rad: float = _DETECTOR.max_viewing_angle_rad
    pixel_noise_px: float = _DETECTOR.pixel_noise_px

    def __post_init__(self) -> None:
        for item in dataclasses.fields(self):
            value = getattr(self, item.name)
            rule = field_rule(DetectorConfig, item.name)
            problem = rule.problem(value, item.type) if rule is not None else None
            if problem is not None:
                raise ValueError(f'{item.name}={value!r}: {problem}')


def tag_detection(
    tag_id: int,
    family: str,
    corners_px: ArrayLike,
    camera_from_tag: ArrayLike,
    size_m: float,
    camera: CameraModel,
    gates: TagGates,
) -> MarkerDetection | Rejection:
    """Return the tag as a MarkerDetection with its pose covariance, or the gate it fails:
    ``corners_px`` (4, 2) px in the camera model's image, ``camera_from_tag`` (4, 4) the tag pose
    in the camera optical frame, ``size_m`` the side of its black square, m."""
    corners = np.asarray(corners_px, dtype=np.float64).reshape(4, 2)
    transform = np.asarray(camera_from_tag, dtype=np.float64)

    def reject(gate: str, reason: str) -> Rejection:
        return Rejection(tag_id, gate, reason, corners)

    if transform.shape != (4, 4) or not np.all(np.isfinite(transform)):
        return reject('no_pose', 'the tag pose is not a finite transform')
    rotation, translation = transform[:3, :3], transform[:3, 3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6):
        return reject('no_pose', 'the tag pose has no valid rotation (a zero quaternion?)')
    if translation[2] <= 0:
        return reject('no_pose', f'the tag is behind the camera (z {translation[2]:.3f} m)')
    if not np.all(np.isfinite(corners)):
        return reject('min_side_px', 'the corners are not finite')
    side_px = float(side_lengths(corners).min())
    if side_px < gates.min_side_px:
        return reject('min_side_px', f'side {side_px:.1f} px < min_side_px {gates.min_side_px:g}')
    objects = marker_object_points(size_m)
    in_camera = objects @ rotation.T + translation
    if np.any(in_camera[:, 2] <= 0):
        return reject('no_pose', 'a corner of the tag is behind the camera')
    projected = camera.project(in_camera)
    distances = np.linalg.norm(corners[:, None, :] - projected[None, :, :], axis=2)
    error_px = float(np.sqrt(np.mean(distances.min(axis=1) ** 2)))
    if not error_px <= gates.max_reprojection_error_px:
        return reject(
            'max_reprojection_error_px',
            f'corners {error_px:.2f} px from the tag projected at its pose > '
            f'max_reprojection_error_px {gates.max_reprojection_error_px:g} (is the tag size '
            "or the camera model the detector's?)",
        )
    range_m = float(np.linalg.norm(translation))
    if range_m > gates.max_range_m:
        return reject('max_range_m', f'range {range_m:.2f} m > max_range_m {gates.max_range_m:g}')
    angle = viewing_angle_either_side(rotation, translation)
    if angle > gates.max_viewing_angle_rad:
        return reject(
            'max_viewing_angle_rad',
            f'viewing angle {math.degrees(angle):.1f} deg > max_viewing_angle_rad '
            f'{gates.max_viewing_angle_rad:g}',
        )
    jacobian = corner_jacobian(objects, rotation, translation, camera)
    covariance = pose_covariance(jacobian, gates.pixel_noise_px)
    if covariance is None:
        return reject('degenerate_pose', 'degenerate corner geometry: the covariance is undefined')
    return MarkerDetection(
        id=tag_id,
        dictionary=family,
        corners_px=corners,
        rotation=rotation,
        translation_m=translation,
        covariance=covariance,
        reprojection_error_px=error_px,
        marker_size_m=size_m,
        side_px=side_px,
        range_m=range_m,
        viewing_angle_rad=angle,
    )


def viewing_angle_either_side(rotation: ArrayLike, translation: ArrayLike) -> float:
    """Return the angle (rad, <= pi/2) between the tag plane's normal, whichever way it
    points, and the line of sight to the camera."""
    normal = np.asarray(rotation, dtype=np.float64)[:, 2]
    towards_camera = -np.asarray(translation, dtype=np.float64)
    cosine = abs(float(normal @ towards_camera)) / float(np.linalg.norm(towards_camera))
    return float(np.arccos(min(cosine, 1.0)))
