"""Fiducial detection: cv2.aruco candidates, edge-refined corners, pose, covariance, gates.
Pipeline and cv2.aruco settings: docs/design/marker_core.md"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from marker_detector.core.candidates import MarkerCorners, locate_markers
from marker_detector.core.detector_config import (
    CORNER_REFINEMENTS,
    DETECTOR_PROFILES,
    DetectorConfig,
)
from marker_detector.core.dictionaries import get_dictionary
from marker_detector.core.edges import side_lengths
from marker_detector.core.pose import (
    MarkerPose,
    pose_covariance,
    solve_marker_poses,
    viewing_angle_rad,
)
from marker_detector.core.roi import Box
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel


@dataclass(frozen=True, eq=False)
class MarkerDetection:
    """One accepted marker with its pose in the camera optical frame: corners_px (4, 2) raw px,
    OpenCV order; rotation (3, 3), translation_m (3,) m, marker to camera; covariance (6, 6)
    (``core.pose``); errors and side_px (the shortest side) px, range_m m, viewing_angle_rad
    between marker normal and line of sight."""

    id: int
    dictionary: str
    corners_px: FloatArray
    rotation: FloatArray
    translation_m: FloatArray
    covariance: FloatArray
    reprojection_error_px: float
    marker_size_m: float
    side_px: float
    range_m: float
    viewing_angle_rad: float
    alternative_error_px: float = math.inf


@dataclass(frozen=True, eq=False)
class Rejection:
    """A decoded marker dropped by a gate: ``gate`` the setting (or 'no_pose',
    'degenerate_pose'), ``reason`` the sentence with the measured value."""

    id: int
    gate: str
    reason: str
    corners_px: FloatArray | None = None


@dataclass(frozen=True)
class DetectionResult:
    """Accepted detections and rejected markers of one image."""

    detections: list[MarkerDetection]
    rejections: list[Rejection]


def _set_parameter(
    params: cv2.aruco.DetectorParameters, names: tuple[str, ...], value: float, *, essential: bool
) -> None:
    for name in names:
        if hasattr(params, name):
            setattr(params, name, value)
            return
    if essential:
        raise RuntimeError(
            f'cv2.aruco.DetectorParameters has no {" / ".join(names)} in OpenCV '
            f'{cv2.__version__}; marker_detector needs OpenCV 4.7 or newer'
        )


def make_detector(config: DetectorConfig) -> cv2.aruco.ArucoDetector:
    """Return a cv2.aruco.ArucoDetector for ``config``; RuntimeError before OpenCV 4.7."""
    for name in (
        'ArucoDetector',
        'DetectorParameters',
        CORNER_REFINEMENTS[config.corner_refinement],
    ):
        if not hasattr(cv2.aruco, name):
            raise RuntimeError(
                f'cv2.aruco has no {name} in OpenCV {cv2.__version__}; marker_detector needs '
                'OpenCV 4.7 or newer (the ArucoDetector API)'
            )
    params = cv2.aruco.DetectorParameters()
    windows = DETECTOR_PROFILES[config.detector_profile].threshold_windows_px
    method = getattr(cv2.aruco, CORNER_REFINEMENTS[config.corner_refinement])
    settings: list[tuple[tuple[str, ...], float, bool]] = [
        (('cornerRefinementMethod',), int(method), True),
        (('cornerRefinementWinSize',), 5, True),
        (('relativeCornerRefinmentWinSize', 'relativeCornerRefinementWinSize'), 0.5, False),
        (('cornerRefinementMaxIterations',), 50, True),
        (('cornerRefinementMinAccuracy',), 0.01, True),
        (('adaptiveThreshWinSizeMin',), windows[0], True),
        (('adaptiveThreshWinSizeMax',), windows[1], True),
        (('adaptiveThreshWinSizeStep',), windows[2], True),
        (('perspectiveRemovePixelPerCell',), 4, True),
        (('perspectiveRemoveIgnoredMarginPerCell',), 0.25, True),
        (('errorCorrectionRate',), config.error_correction_rate, True),
        (('minDistanceToBorder',), 0, True),
    ]
    for names, value, essential in settings:
        _set_parameter(params, names, value, essential=essential)
    return cv2.aruco.ArucoDetector(get_dictionary(config.dictionary), params)


def as_gray(image: NDArray[np.uint8], camera: CameraModel | None = None) -> NDArray[np.uint8]:
    """Return ``image`` (H, W) uint8 gray or (H, W, 3) BGR as (H, W) gray; ValueError if bad."""
    if not isinstance(image, np.ndarray):
        raise ValueError(f'image must be a numpy array, got {type(image).__name__}')
    if image.size == 0:
        raise ValueError(f'image is empty (shape {image.shape})')
    if image.dtype != np.uint8:
        raise ValueError(f'image dtype is {image.dtype}; expected uint8 (8-bit gray or BGR)')
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        gray: NDArray[np.uint8] = np.asarray(
            cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_BGR2GRAY), dtype=np.uint8
        )
    elif image.ndim == 2:
        gray = np.ascontiguousarray(image)
    else:
        raise ValueError(f'image has shape {image.shape}; expected (H, W) gray or (H, W, 3) BGR')
    if camera is not None:
        camera.check_image_size(gray.shape[1], gray.shape[0])
    return gray


def detect_markers(
    image: NDArray[np.uint8],
    camera: CameraModel,
    config: DetectorConfig,
    detector: cv2.aruco.ArucoDetector | None = None,
    boxes: list[Box] | None = None,
) -> DetectionResult:
    """Return the markers in a raw camera image (H, W) gray or (H, W, 3) BGR uint8; ``detector``
    from ``make_detector(config)`` (None: built here), ``boxes`` the regions to search (None: all,
    ``core.roi``). ValueError for a bad image or size."""
    gray = as_gray(image, camera)
    detector = detector if detector is not None else make_detector(config)
    detections: list[MarkerDetection] = []
    rejections: list[Rejection] = []
    candidates: list[MarkerCorners] = []
    located = (
        locate_markers(gray, config, detector, camera)
        if boxes is None
        else [m for box in boxes for m in locate_markers(gray, config, detector, camera, box)]
    )
    for marker in located:
        rejection = _image_gate(marker, config)
        if rejection is not None:
            rejections.append(rejection)
        else:
            candidates.append(marker)
    poses = solve_marker_poses(
        np.array([marker.corners_px for marker in candidates]).reshape(-1, 4, 2),
        [config.marker_size_m(marker.id) for marker in candidates],
        camera,
    )
    for marker, pose in zip(candidates, poses, strict=True):
        outcome = _evaluate(marker, pose, config)
        if isinstance(outcome, MarkerDetection):
            detections.append(outcome)
        else:
            rejections.append(outcome)
    return DetectionResult(detections, rejections)


def _image_gate(marker: MarkerCorners, config: DetectorConfig) -> Rejection | None:
    """Return the rejection by the gates that need no pose (None if it passes them)."""
    if config.allowed_ids and marker.id not in config.allowed_ids:
        return Rejection(
            marker.id, 'allowed_ids', f'id {marker.id} not in allowed_ids', marker.corners_px
        )
    side_px = float(side_lengths(marker.corners_px).min())
    if side_px < config.min_side_px:
        return Rejection(
            marker.id,
            'min_side_px',
            f'side {side_px:.1f} px < min_side_px {config.min_side_px:g}',
            marker.corners_px,
        )
    return None


def _evaluate(
    marker: MarkerCorners, pose: MarkerPose | None, config: DetectorConfig
) -> MarkerDetection | Rejection:
    """Return the detection of one marker, or the first pose quality gate it fails."""
    corners = marker.corners_px

    def reject(gate: str, reason: str) -> Rejection:
        return Rejection(marker.id, gate, reason, corners)

    if pose is None:
        return reject(
            'no_pose', 'no pose: solvePnP IPPE_SQUARE found no solution in front of the camera'
        )
    if pose.reprojection_error_px > config.max_reprojection_error_px:
        return reject(
            'max_reprojection_error_px',
            f'reprojection error {pose.reprojection_error_px:.2f} px > '
            f'max_reprojection_error_px {config.max_reprojection_error_px:g}',
        )
    range_m = float(np.linalg.norm(pose.translation_m))
    if range_m > config.max_range_m:
        return reject('max_range_m', f'range {range_m:.2f} m > max_range_m {config.max_range_m:g}')
    angle = viewing_angle_rad(pose.rotation, pose.translation_m)
    limit = config.max_viewing_angle_rad
    if angle > limit:
        return reject(
            'max_viewing_angle_rad',
            f'viewing angle {math.degrees(angle):.1f} deg > max_viewing_angle_rad '
            f'{limit:g} ({math.degrees(limit):.1f} deg)',
        )
    covariance = pose_covariance(pose.jacobian, config.pixel_noise_px)
    if covariance is None:
        return reject(
            'degenerate_pose', 'degenerate corner geometry: the pose covariance is undefined'
        )
    return MarkerDetection(
        id=marker.id,
        dictionary=config.dictionary,
        corners_px=corners,
        rotation=pose.rotation,
        translation_m=pose.translation_m,
        covariance=covariance,
        reprojection_error_px=pose.reprojection_error_px,
        marker_size_m=config.marker_size_m(marker.id),
        side_px=float(side_lengths(corners).min()),
        range_m=range_m,
        viewing_angle_rad=angle,
        alternative_error_px=pose.alternative_error_px,
    )
