"""Markers in a gray image: cv2.aruco's detections with edge-refined corners, and its
rejected candidates decoded again from refined corners (no pose, no quality gates)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from marker_detector.core.decoding import decode_quad, may_be_marker
from marker_detector.core.detector_config import DETECTOR_PROFILES, DetectorConfig
from marker_detector.core.edges import EdgeSettings, refine_corners_batch, side_lengths
from marker_detector.core.roi import Box
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel

REDECODE_SIDE_SLACK_PX = 2.0  # rough contour corners sit up to ~1 px inside at each end
OPENCV_MIN_PERIMETER_RATE = 0.03  # cv2.aruco's default minMarkerPerimeterRate


@dataclass(frozen=True, eq=False)
class MarkerCorners:
    """One decoded marker before pose estimation: id, raw-image corners (4, 2) px, ``source``
    'aruco' or 'redecoded', and whether the edges moved the corners."""

    id: int
    corners_px: FloatArray
    source: str
    edge_refined: bool


def locate_markers(
    gray: NDArray[np.uint8],
    config: DetectorConfig,
    detector: cv2.aruco.ArucoDetector,
    camera: CameraModel | None = None,
    box: Box | None = None,
) -> list[MarkerCorners]:
    """Return the decoded markers of a gray image with their (edge-refined) corners, ungated;
    ``box`` (x0, y0, x1, y1) px: search only there (corners stay image pixels)."""
    region = gray if box is None else np.ascontiguousarray(gray[box[1] : box[3], box[0] : box[2]])
    params = detector.getDetectorParameters()
    floor = candidate_perimeter_rate(config.min_side_px, region.shape)
    if params.minMarkerPerimeterRate != floor:
        params.minMarkerPerimeterRate = floor
        detector.setDetectorParameters(params)
    corners, ids, rejected = detector.detectMarkers(region)
    dictionary = detector.getDictionary()
    cells = int(dictionary.markerSize) + 2 * int(params.markerBorderBits)
    found = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
    if box is not None:
        offset = np.array([box[0], box[1]], dtype=np.float32)
        found = found + offset.astype(np.float64)
        rejected = [np.asarray(quad, dtype=np.float32) + offset for quad in rejected]
    marker_ids = [] if ids is None else [int(i) for i in ids.ravel()]
    if not (config.edge_refinement or config.redecode_rejected):
        return [
            MarkerCorners(i, c, 'aruco', False) for i, c in zip(marker_ids, found, strict=True)
        ]
    image = gray.astype(np.float32)
    edges = EdgeSettings(iterations=DETECTOR_PROFILES[config.detector_profile].edge_iterations)
    refined_ok = np.zeros(len(found), dtype=bool)
    if config.edge_refinement and len(found):
        found, refined_ok = refine_corners_batch(image, found, cells, camera, edges)
    markers = [
        MarkerCorners(marker_id, quad, 'aruco', bool(ok))
        for marker_id, quad, ok in zip(marker_ids, found, refined_ok, strict=True)
    ]
    if config.redecode_rejected:
        markers += _redecode(image, rejected, markers, cells, detector, config, camera, edges)
    return markers


def candidate_perimeter_rate(min_side_px: float, shape: tuple[int, ...]) -> float:
    """Return cv2.aruco's minMarkerPerimeterRate for an image of ``shape`` (H, W, ...):
    no contour whose sides cannot reach ``min_side_px``, never below OpenCV's default."""
    perimeter = 4.0 * max(min_side_px - REDECODE_SIDE_SLACK_PX, 0.0)
    return max(OPENCV_MIN_PERIMETER_RATE, perimeter / max(shape[0], shape[1]))


def _redecode(
    image: NDArray[np.float32],
    rejected: Sequence[NDArray[Any]],
    markers: list[MarkerCorners],
    cells: int,
    detector: cv2.aruco.ArucoDetector,
    config: DetectorConfig,
    camera: CameraModel | None,
    edges: EdgeSettings,
) -> list[MarkerCorners]:
    """Return the rejected candidates that decode from edge-refined corners."""
    quads = []
    for quad in rejected:
        raw = _clockwise(np.asarray(quad, dtype=np.float64).reshape(4, 2))
        if (
            side_lengths(raw).min() >= config.min_side_px - REDECODE_SIDE_SLACK_PX
            and not _overlaps(raw, markers)
            and may_be_marker(image, raw, cells)
        ):
            quads.append(raw)
    if not quads:
        return []
    refined, ok = refine_corners_batch(image, np.array(quads), cells, camera, edges)
    params = detector.getDetectorParameters()
    decoded_markers: list[MarkerCorners] = []
    for quad in refined[ok]:
        if _overlaps(quad, decoded_markers):
            continue
        decoded = decode_quad(
            image,
            quad,
            detector.getDictionary(),
            border_bits=int(params.markerBorderBits),
            error_correction_rate=config.error_correction_rate,
            max_border_error_rate=float(params.maxErroneousBitsInBorderRate),
        )
        if decoded is not None:
            decoded_markers.append(MarkerCorners(decoded[0], decoded[1], 'redecoded', True))
    return decoded_markers


def _clockwise(corners: FloatArray) -> FloatArray:
    """Return the quad with its corners running clockwise on screen (image y down)."""
    x, y = corners[:, 0], corners[:, 1]
    area = np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    return corners if area > 0 else corners[::-1].copy()


def _overlaps(corners: FloatArray, markers: list[MarkerCorners]) -> bool:
    centre = corners.mean(axis=0)
    for marker in markers:
        contour = marker.corners_px.astype(np.float32).reshape(-1, 1, 2)
        if cv2.pointPolygonTest(contour, (float(centre[0]), float(centre[1])), False) >= 0:
            return True
    return False
