"""The reference trajectory's own pose error from images; see docs/design/simulation.md."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.depth import DepthSampling, sample_depth
from slam_sim.core.rgbd_depth import camera_points

RATIO_TEST = 0.75
"""Lowe's ratio: a match is kept when its descriptor distance is below this share of the
second nearest's (Lowe 2004, section 7.1)."""
INLIER_CHI2_2DOF = 9.21
"""chi-square(2) at 99 %: a match is a PnP inlier within sqrt(this) pixel sigmas."""


@dataclass(frozen=True)
class ReferencePoseError:
    """The reference's per-axis rotation sigma (rad) and centre sigma (m) per separation (s)."""

    separations_s: tuple[float, ...]
    rotation_sigmas_rad: tuple[float, ...]
    translation_sigmas_m: tuple[float, ...]

    def __post_init__(self) -> None:
        """Reject tables that cannot be interpolated."""
        separations = np.asarray(self.separations_s, dtype=np.float64)
        if not len(separations) or any(
            np.shape(column) != separations.shape
            for column in (self.rotation_sigmas_rad, self.translation_sigmas_m)
        ):
            raise ValueError('reference error: give one rotation and one translation sigma per '
                             'separation, at least one')  # fmt: skip
        if np.any(np.diff(separations) <= 0) or not np.all(np.isfinite(separations)):
            raise ValueError(f'reference error separations {self.separations_s}: must increase')
        for name, column in (
            ('rotation_sigmas_rad', self.rotation_sigmas_rad),
            ('translation_sigmas_m', self.translation_sigmas_m),
        ):
            values = np.asarray(column, dtype=np.float64)
            if not np.all(np.isfinite(values) & (values >= 0)):
                raise ValueError(f'reference error {name} {column}: must be finite and >= 0')

    def at(self, separation_s: float) -> tuple[float, float]:
        """Return (rotation sigma rad, centre sigma m) for poses ``separation_s`` apart."""
        s = abs(separation_s)
        return (
            float(np.interp(s, self.separations_s, self.rotation_sigmas_rad)),
            float(np.interp(s, self.separations_s, self.translation_sigmas_m)),
        )

    def to_json(self) -> dict[str, list[float]]:
        """Return the table as a JSON object (``from_json`` reads it back)."""
        return {
            'separations_s': list(self.separations_s),
            'rotation_sigmas_rad': list(self.rotation_sigmas_rad),
            'translation_sigmas_m': list(self.translation_sigmas_m),
        }

    @classmethod
    def from_json(cls, table: dict[str, Any]) -> ReferencePoseError:
        """Return the table of a JSON object; KeyError, TypeError or ValueError."""
        return cls(
            tuple(float(v) for v in table['separations_s']),
            tuple(float(v) for v in table['rotation_sigmas_rad']),
            tuple(float(v) for v in table['translation_sigmas_m']),
        )


@dataclass(frozen=True)
class PairError:
    """One pair's rotation (3,) rad and centre (3,) m errors, PnP variances (6,), inliers."""

    rotation_rad: FloatArray
    centre_m: FloatArray
    own_variances: FloatArray
    inliers: int


@dataclass(frozen=True)
class ImageFeatures:
    """An image's SIFT keypoints (N, 2) px and descriptors (N, 128)."""

    pixels: FloatArray
    descriptors: FloatArray

    @classmethod
    def of(cls, image: np.ndarray, max_features: int = 1500) -> ImageFeatures:
        """Return the SIFT features of a grey or BGR image (uint8)."""
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        sift = cv2.SIFT_create(max_features)  # type: ignore[attr-defined]
        keypoints, descriptors = sift.detectAndCompute(grey, None)
        if descriptors is None:
            return cls(np.zeros((0, 2)), np.zeros((0, 128), dtype=np.float32))
        return cls(np.array([k.pt for k in keypoints], dtype=np.float64), descriptors)


def matches(first: ImageFeatures, second: ImageFeatures) -> tuple[np.ndarray, np.ndarray]:
    """Return the indices (M,), (M,) of the matches that pass the ratio test."""
    if len(first.pixels) < 2 or len(second.pixels) < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(first.descriptors, second.descriptors, k=2)
    kept = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO_TEST * p[1].distance]
    return (
        np.array([m.queryIdx for m in kept], dtype=np.int64),
        np.array([m.trainIdx for m in kept], dtype=np.int64),
    )


def pair_error(
    camera: CameraModel,
    first: tuple[ImageFeatures, FloatArray, FloatArray],
    second: tuple[ImageFeatures, FloatArray],
    *,
    pixel_sigma_px: float = 1.0,
    min_inliers: int = 20,
    sampling: DepthSampling | None = None,
) -> PairError | None:
    """Return the reference's relative pose error between two images, None if too few inliers."""
    (features_a, depth_a, pose_a), (features_b, pose_b) = first, second
    index_a, index_b = matches(features_a, features_b)
    depth = sample_depth(depth_a, features_a.pixels[index_a], sampling)
    seen = np.isfinite(depth)
    if int(np.count_nonzero(seen)) < min_inliers:
        return None
    points = camera_points(camera, features_a.pixels[index_a[seen]], depth[seen])
    pixels = features_b.pixels[index_b[seen]][np.all(np.isfinite(points), axis=1)]
    points = points[np.all(np.isfinite(points), axis=1)]
    reference = np.linalg.inv(pose_b) @ pose_a  # camera a -> camera b
    matrix, distortion = camera.calibration_matrix, camera.dist_coeffs
    start_rvec = cv2.Rodrigues(reference[:3, :3])[0]
    start_tvec = reference[:3, 3].reshape(3, 1).copy()
    cv2.setRNGSeed(0)
    found, rvec, tvec, inliers = cv2.solvePnPRansac(
        points, pixels, matrix, distortion, start_rvec, start_tvec, useExtrinsicGuess=True,
        iterationsCount=300, reprojectionError=float(np.sqrt(INLIER_CHI2_2DOF) * pixel_sigma_px),
    )  # fmt: skip
    if not found or inliers is None or len(inliers) < min_inliers:
        return None
    kept = inliers[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(points[kept], pixels[kept], matrix, distortion, rvec, tvec)
    rotation = cv2.Rodrigues(rvec)[0]
    projected, jacobian = cv2.projectPoints(points[kept], rvec, tvec, matrix, distortion)
    residual_variance = float(np.mean((projected[:, 0, :] - pixels[kept]) ** 2))
    pose_jacobian = jacobian[:, :6]
    own = np.linalg.inv(pose_jacobian.T @ pose_jacobian) * residual_variance
    centre_images = -rotation.T @ tvec[:, 0]
    centre_reference = -reference[:3, :3].T @ reference[:3, 3]
    # the centre's variance, -R^T t to first order in t (the rotation's part is the smaller)
    centre_covariance = rotation.T @ own[3:, 3:] @ rotation
    return PairError(
        Rotation.from_matrix(rotation @ reference[:3, :3].T).as_rotvec(),
        centre_images - centre_reference,
        np.concatenate([np.diag(own[:3, :3]), np.diag(centre_covariance)]),
        len(kept),
    )


@dataclass(frozen=True)
class BandErrors:
    """One band's pairs: separations (P,) s, errors (P, 6), PnP variances (P, 6), inliers."""

    separations_s: FloatArray
    errors: FloatArray
    own_variances: FloatArray
    inliers: np.ndarray

    def sigmas(self) -> tuple[float, float]:
        """Return the per-axis (rotation rad, centre m) sigma, less the PnP's own variance."""
        excess = np.mean(self.errors**2, axis=0) - np.mean(self.own_variances, axis=0)
        return (
            float(np.sqrt(max(float(np.mean(excess[:3])), 0.0))),
            float(np.sqrt(max(float(np.mean(excess[3:])), 0.0))),
        )

    def summary(self) -> dict[str, Any]:
        """Return the band's figures for a report (degrees and metres)."""
        rotation, centre = self.sigmas()
        return {
            'pairs': len(self.separations_s),
            'median_separation_s': float(np.median(self.separations_s)),
            'median_inliers': int(np.median(self.inliers)),
            'rms_rotation_deg': np.degrees(np.sqrt(np.mean(self.errors[:, :3] ** 2, 0))).tolist(),
            'rms_centre_m': np.sqrt(np.mean(self.errors[:, 3:] ** 2, 0)).tolist(),
            'own_rotation_sigma_deg': float(
                np.degrees(np.sqrt(np.mean(self.own_variances[:, :3])))
            ),
            'rotation_sigma_deg': float(np.degrees(rotation)),
            'centre_sigma_m': centre,
        }


def reference_pose_error(
    camera: CameraModel,
    stamps_ns: np.ndarray,
    frames: Mapping[int, tuple[Callable[[], np.ndarray], FloatArray | None, FloatArray]],
    bands_s: tuple[tuple[float, float], ...],
    *,
    pixel_sigma_px: float = 1.0,
) -> tuple[ReferencePoseError, list[BandErrors]]:
    """Return a static stretch's reference pose error table and bands; ValueError."""
    with_depth = sorted(k for k, (_, depth, _) in frames.items() if depth is not None)
    features = {k: ImageFeatures.of(frames[k][0]()) for k in with_depth}
    gathered: list[list[tuple[float, PairError]]] = [[] for _ in bands_s]
    for position, a in enumerate(with_depth):
        for b in with_depth[position + 1 :]:
            separation = (int(stamps_ns[b]) - int(stamps_ns[a])) * 1e-9
            band = next((i for i, (lo, hi) in enumerate(bands_s) if lo <= separation < hi), None)
            if band is None:
                continue
            found = pair_error(
                camera, (features[a], frames[a][1], frames[a][2]),  # type: ignore[arg-type]
                (features[b], frames[b][2]), pixel_sigma_px=pixel_sigma_px,
            )  # fmt: skip
            if found is not None:
                gathered[band].append((separation, found))
    bands = [
        BandErrors(
            np.array([s for s, _ in pairs]),
            np.array([np.concatenate([p.rotation_rad, p.centre_m]) for _, p in pairs]),
            np.array([p.own_variances for _, p in pairs]),
            np.array([p.inliers for _, p in pairs]),
        )
        for pairs in gathered
        if pairs
    ]
    if not bands:
        raise ValueError('no pair of images with depth and pose in the static stretch matched')
    sigmas = [band.sigmas() for band in bands]
    return (
        ReferencePoseError(
            tuple(float(np.median(band.separations_s)) for band in bands),
            tuple(rotation for rotation, _ in sigmas),
            tuple(centre for _, centre in sigmas),
        ),
        bands,
    )
