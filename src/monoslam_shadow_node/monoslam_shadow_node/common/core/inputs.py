"""The input types of the processors: one image's feature tracks and one camera pose."""

from __future__ import annotations

from dataclasses import dataclass

from slam_core.arrays import FloatArray, IntArray


@dataclass(frozen=True, eq=False)
class Features:
    """One FeatureTrackArray: stamp (int ns), frame, ids (M,), raw pixels (M, 2) (may hold NaN)."""

    stamp_ns: int
    frame_id: str
    ids: IntArray
    pixels: FloatArray


@dataclass(frozen=True, eq=False)
class CameraPose:
    """One camera pose: stamp (int ns), world frame, R_world_camera (3, 3), centre (3,) m,
    covariance (6, 6) or None, and cross-covariances (K, 6, 6) with ``cross_stamps``."""

    stamp_ns: int
    frame_id: str
    rotation: FloatArray
    centre: FloatArray
    covariance: FloatArray | None
    cross_stamps: tuple[int, ...] = ()
    cross_covariances: FloatArray | None = None
