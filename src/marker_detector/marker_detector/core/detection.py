"""Fiducial detection: cv2.aruco candidates, edge-refined corners, pose, covariance, gates.

Pipeline of ``detect_markers`` on one image (raw, distorted, as the camera delivers it):

1. cv2.aruco's ArucoDetector finds and decodes markers (``make_detector``: parameters tuned
   for accuracy, AprilTag dictionaries with bit-error correction, see ``core.dictionaries``);
2. every marker's corners are re-measured from its four outer edges (``core.edges``), and
   candidates cv2.aruco rejected are decoded again from those refined corners;
3. the pose comes from solvePnP IPPE_SQUARE with K and D (lens distortion is handled inside
   PnP), the better of its two solutions refined by a Gauss-Newton step; the covariance from
   the reprojection Jacobian (``core.pose``);
4. quality gates drop markers that are not allowed, too small in the image, badly explained by
   their pose, too far or seen too obliquely; each drop is a ``Rejection`` with the reason.

Frames and conventions are those of ``core.pose`` (camera optical frame; marker x right, y up,
z out of the face) and ``core.camera`` (pixel centres at integer coordinates).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import cv2
import numpy as np
from numpy.typing import NDArray

from marker_detector.core.candidates import DETECTOR_PROFILES, MarkerCorners, locate_markers
from marker_detector.core.dictionaries import DEFAULT_DICTIONARY, DICTIONARIES, get_dictionary
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

CORNER_REFINEMENTS = {
    'subpix': 'CORNER_REFINE_SUBPIX',
    'contour': 'CORNER_REFINE_CONTOUR',
    'apriltag': 'CORNER_REFINE_APRILTAG',
    'none': 'CORNER_REFINE_NONE',
}


@dataclass(frozen=True)
class DetectorConfig:
    """Detector settings; invalid values raise ValueError naming the setting.

    ``marker_sizes_m`` maps marker id -> black-border side length (m) for markers that differ
    from ``default_marker_size_m``. ``allowed_ids`` empty means every id. Limits may be inf
    (no gate). ``max_viewing_angle_rad`` is the angle between the marker normal and the line
    of sight. ``pixel_noise_px`` is the corner noise sigma behind the pose covariance.
    ``edge_refinement`` re-measures corners from the marker edges (``core.edges``);
    ``redecode_rejected`` decodes cv2.aruco's rejected candidates again from refined
    corners; ``error_correction_rate`` is the fraction of the dictionary's bit-correction
    capability used (cv2.aruco's errorCorrectionRate); ``detector_profile`` trades speed
    for recall: the adaptive-threshold passes and edge-fit iterations (``DETECTOR_PROFILES``).
    """

    dictionary: str = DEFAULT_DICTIONARY
    default_marker_size_m: float = 0.16
    marker_sizes_m: Mapping[int, float] = field(default_factory=dict)
    corner_refinement: str = 'subpix'
    min_side_px: float = 12.0
    max_reprojection_error_px: float = 2.0
    max_range_m: float = 8.0
    max_viewing_angle_rad: float = math.radians(70.0)
    allowed_ids: tuple[int, ...] = ()
    pixel_noise_px: float = 0.5
    edge_refinement: bool = True
    redecode_rejected: bool = True
    error_correction_rate: float = 0.6
    detector_profile: str = 'accurate'

    def __post_init__(self) -> None:
        sizes = dict(self.marker_sizes_m)
        ids = tuple(self.allowed_ids)
        bad_size = [(k, v) for k, v in sizes.items() if not _is_id(k) or not _positive(v, True)]
        bad_ids = [marker_id for marker_id in ids if not _is_id(marker_id)]
        checks: list[tuple[bool, str, object, str]] = [
            (self.dictionary in DICTIONARIES, 'dictionary', self.dictionary,
             f'must be one of {", ".join(DICTIONARIES)}'),
            (_positive(self.default_marker_size_m, True), 'default_marker_size_m',
             self.default_marker_size_m, 'must be a finite number > 0 (m)'),
            (not bad_size, 'marker_sizes_m', sizes,
             f'entry {bad_size[:1]} needs an id (int >= 0) and a finite size > 0 (m)'),
            (self.corner_refinement in CORNER_REFINEMENTS, 'corner_refinement',
             self.corner_refinement, f'must be one of {", ".join(CORNER_REFINEMENTS)}'),
            (_number(self.min_side_px) and 0 <= self.min_side_px < math.inf, 'min_side_px',
             self.min_side_px, 'must be a finite number >= 0 (px)'),
            (_positive(self.max_reprojection_error_px), 'max_reprojection_error_px',
             self.max_reprojection_error_px, 'must be a number > 0 (px; inf: no limit)'),
            (_positive(self.max_range_m), 'max_range_m', self.max_range_m,
             'must be a number > 0 (m; inf: no limit)'),
            (_number(self.max_viewing_angle_rad) and 0 < self.max_viewing_angle_rad <= math.pi / 2,
             'max_viewing_angle_rad', self.max_viewing_angle_rad, 'must be in (0, pi/2] rad'),
            (not bad_ids, 'allowed_ids', ids, f'{bad_ids[:1]} is not an int >= 0'),
            (_positive(self.pixel_noise_px, True), 'pixel_noise_px', self.pixel_noise_px,
             'must be a finite number > 0 (px)'),
            (_number(self.error_correction_rate) and 0 <= self.error_correction_rate <= 1,
             'error_correction_rate', self.error_correction_rate, 'must be in [0, 1]'),
            (self.detector_profile in DETECTOR_PROFILES, 'detector_profile',
             self.detector_profile, f'must be one of {", ".join(DETECTOR_PROFILES)}'),
        ]  # fmt: skip
        for ok, name, value, reason in checks:
            if not ok:
                raise ValueError(f'marker_detector setting {name}={value!r}: {reason}')
        object.__setattr__(self, 'marker_sizes_m', MappingProxyType(sizes))
        object.__setattr__(self, 'allowed_ids', ids)

    def marker_size_m(self, marker_id: int) -> float:
        """Return the side length (m) of marker ``marker_id``."""
        return self.marker_sizes_m.get(marker_id, self.default_marker_size_m)


def _number(value: object) -> bool:
    return isinstance(value, int | float | np.floating | np.integer) and not isinstance(
        value, bool
    )


def _positive(value: object, finite: bool = False) -> bool:
    """True for a number > 0 (finite if asked; inf passes otherwise, NaN never)."""
    if not _number(value):
        return False
    number = float(value)  # type: ignore[arg-type]
    return number > 0 and (math.isfinite(number) or (not finite and number == math.inf))


def _is_id(value: object) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool) and bool(value >= 0)


@dataclass(frozen=True, eq=False)
class MarkerDetection:
    """One accepted marker with its pose in the camera optical frame.

    corners_px (4, 2) raw image px, OpenCV order (top-left, top-right, bottom-right,
    bottom-left); rotation (3, 3) and translation_m (3,) map marker points into the camera
    frame; covariance (6, 6) over (x, y, z, rot_x, rot_y, rot_z), see ``core.pose``;
    reprojection_error_px is the RMS over the corners; side_px the shortest side; range_m
    |translation_m|; viewing_angle_rad between marker normal and line of sight;
    alternative_error_px the reprojection error of the other IPPE pose (near
    reprojection_error_px: the orientation is ambiguous).
    """

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
    """A decoded marker dropped by a quality gate: ``gate`` is the setting that dropped it
    (e.g. 'max_range_m'; 'no_pose' or 'degenerate_pose' when no usable pose exists),
    ``reason`` the sentence with the measured value."""

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
    """Return a cv2.aruco.ArucoDetector for ``config`` (works on OpenCV 4.7+ and 5.x).

    Only the ArucoDetector object API is used. Against OpenCV's defaults (measured on the
    three AprilTag photos and synthetic renders, see the tests):

    - subpixel windows of half a cell (relativeCornerRefinmentWinSize 0.5, at most 5 px),
      50 iterations to 0.01 px. cornerSubPix only seeds the edge fit (``core.edges``), which
      removes the 0.2-0.3 px inward bias cornerSubPix leaves at any window size (ranges 1-2 %
      long); windows of a whole cell pulled corners of small blurred markers in the photos
      up to 4.7 px towards the marker's inner pattern;
    - cells read over their central half (perspectiveRemoveIgnoredMarginPerCell 0.25 instead
      of 0.13): small and blurred markers decode (recall 28 % -> 56 % on the photo with the
      smallest tags, before the bit correction of ``core.dictionaries``);
    - candidates whose contour comes within 3 px of the image border are kept
      (minDistanceToBorder 0): the default also dropped fully visible markers whose black
      border merges, in the thresholded image, with a dark (vignetted) image corner (slam_sim
      office renders: recall within the gates 97.9 % -> 99.95 %);
    - adaptive-threshold windows from ``config.detector_profile`` (``DETECTOR_PROFILES``).
    """
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
    """Return the markers in a raw camera image (H, W) gray or (H, W, 3) BGR uint8.

    ``detector`` from ``make_detector(config)``; pass it when calling per frame (built here
    if None). ``boxes``: look only in these regions (``core.roi``); None: the whole image.
    Raises ValueError for an empty image, a wrong dtype or shape, or a size that differs
    from the camera's.
    """
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
