"""The input types of the processors: one image's feature tracks and one camera pose."""

from __future__ import annotations

from dataclasses import dataclass

from slam_core.arrays import FloatArray, IntArray


@dataclass(frozen=True, eq=False)
class Features:
    """One FeatureTrackArray: image stamp (int ns), camera frame, track ids (M,) and raw
    pixels (M, 2) (u right, v down; may hold NaN, the core drops those)."""

    stamp_ns: int
    frame_id: str
    ids: IntArray
    pixels: FloatArray


@dataclass(frozen=True, eq=False)
class CameraPose:
    """One PoseWithCovarianceStamped of the camera optical frame: stamp (int ns), world frame
    (header.frame_id), R_world_camera (3, 3), optical centre (3,) m, and the covariance
    (6, 6) over (position, rotation about the world axes), None when all zero; and when the
    source gives them (``pose_links``), the covariances (K, 6, 6) of the pose's error with
    those of its earlier poses stamped ``cross_stamps``."""

    stamp_ns: int
    frame_id: str
    rotation: FloatArray
    centre: FloatArray
    covariance: FloatArray | None
    cross_stamps: tuple[int, ...] = ()
    cross_covariances: FloatArray | None = None
