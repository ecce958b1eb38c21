"""Messages <-> the feature tracker: the predicted pixels, covariances and warps that
monoslam/predicted_features carries."""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.geometry import quaternion
from slam_core.stamps import ns_to_stamp, stamp_to_ns
from monoslam_shadow_node.common.conversions import CDR_ERRORS, cdr_features, deserialized, features_from_message, tracks_cdr
from monoslam_shadow_node.common.core.inputs import Features


def predictions_from_cdr(
    data: bytes, deserialize: Callable[[bytes], Any]
) -> tuple[Features, FloatArray, FloatArray]:
    """Return the predicted pixels of a serialized FeatureTrackArray (``features_from_cdr``)
    with their covariances (K, 2, 2) and warps (K, 2, 2) (``prediction_covariances``,
    ``prediction_warps``), read from the bytes the same way."""
    try:
        stamp_ns, frame_id, tracks = tracks_cdr(data)
    except CDR_ERRORS:
        message = deserialized(data, deserialize)
        return (
            features_from_message(message),
            prediction_covariances(message),
            prediction_warps(message),
        )
    features = cdr_features(stamp_ns, frame_id, tracks)
    return features, _covariances_2x2(tracks['covariance']), tracks['warp'].reshape(-1, 2, 2)


def _covariances_2x2(upper: FloatArray) -> FloatArray:
    """Return the covariances (K, 2, 2) of FeatureTrack.covariance rows (K, 3) [uu, uv, vv]."""
    upper = np.asarray(upper, dtype=np.float64).reshape(-1, 3)
    covariances = np.empty((len(upper), 2, 2))
    covariances[:, 0, 0], covariances[:, 1, 1] = upper[:, 0], upper[:, 2]
    covariances[:, 0, 1] = covariances[:, 1, 0] = upper[:, 1]
    return covariances


def prediction_covariances(message: Any) -> FloatArray:
    """Return the covariances (K, 2, 2), px^2, of a slam_interfaces/FeatureTrackArray's
    predicted pixels (FeatureTrack.covariance [uu, uv, vv]; zeros where not given)."""
    return _covariances_2x2(
        np.array([list(track.covariance) for track in message.tracks], dtype=np.float64)
    )


def prediction_warps(message: Any) -> FloatArray:
    """Return the template warps (K, 2, 2) of a slam_interfaces/FeatureTrackArray's predicted
    pixels (FeatureTrack.warp, row-major; zeros where not given)."""
    warps = np.array([list(track.warp) for track in message.tracks], dtype=np.float64)
    return warps.reshape(-1, 2, 2)
